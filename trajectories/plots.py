"""PNG plots of a flight log: top view of reference vs flown path, and tracking error against time."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from trajectories.flightlog import read_flight_log

__all__ = ["plot_flight_log"]


def plot_flight_log(log_path: str | Path, out_dir: str | Path | None = None) -> list[Path]:
    """Write ``<log>-top.png`` and ``<log>-error.png`` next to the log (or into ``out_dir``).

    Returns the PNG paths. Raises DatasetError for a file that is not a flight log.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = read_flight_log(log_path)
    src = Path(log_path)
    folder = Path(out_dir) if out_dir else src.parent
    folder.mkdir(parents=True, exist_ok=True)
    phase = log["phase"]
    t = log["t_s"]
    title = f"{log.meta.get('plan', src.stem)} ({log.meta.get('autopilot', '?')})"
    out: list[Path] = []

    fig, ax = plt.subplots(figsize=(7, 6))
    ax.plot(log["pos_x_m"], log["pos_y_m"], color="0.6", lw=0.8, label="flown (all phases)")
    pat = phase == "pattern"
    if pat.any():
        ax.plot(log["ref_x_m"][pat], log["ref_y_m"][pat], "k--", lw=1.2, label="reference (pattern)")
        ax.plot(log["pos_x_m"][pat], log["pos_y_m"][pat], color="tab:blue", lw=1.2, label="flown (pattern)")
    ax.set_xlabel("x (m, world ENU)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(f"{title}: top view")
    top = folder / f"{src.stem}-top.png"
    fig.savefig(top, dpi=120, bbox_inches="tight")
    plt.close(fig)
    out.append(top)

    fig, ax = plt.subplots(figsize=(9, 4))
    err = log["err_m"]
    for name in dict.fromkeys(phase.tolist()):
        m = phase == name
        ax.plot(t[m], np.where(np.isnan(err[m]), np.nan, err[m]), ".", ms=1.5, label=str(name))
    for f in log.faults:
        ax.axvline(f["time_s"], color="tab:red", lw=0.8)
        ax.text(
            f["time_s"],
            ax.get_ylim()[1] * 0.95,
            f["kind"],
            rotation=90,
            va="top",
            fontsize=7,
            color="tab:red",
        )
    ax.set_xlabel("flight time (s)")
    ax.set_ylabel("tracking error (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", markerscale=6, fontsize=8)
    ax.set_title(f"{title}: tracking error")
    errp = folder / f"{src.stem}-error.png"
    fig.savefig(errp, dpi=120, bbox_inches="tight")
    plt.close(fig)
    out.append(errp)
    return out
