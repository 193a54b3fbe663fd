"""Library code raises flightkit's own errors (flightkit/errors.py), never a bare ValueError or
RuntimeError: checked on the source, like tests/unit/test_layering.py."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
LIBRARY = ("flightkit", "trajectories", "capture", "estimation")
BARE = ("ValueError", "RuntimeError")

# path -> at most how many bare raises it may still hold, and why. Keep it short; shrink it.
ALLOWED: dict[str, int] = {}


def bare_raises(path: Path, root: Path = ROOT) -> list[str]:
    """``file:line: raise X(...)`` for each ``raise ValueError`` / ``raise RuntimeError`` in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    hits: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Raise) or node.exc is None:
            continue
        exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
        if isinstance(exc, ast.Name) and exc.id in BARE:
            hits.append((node.lineno, f"{path.relative_to(root)}:{node.lineno}: raise {exc.id}"))
    return [h for _, h in sorted(hits)]


def test_library_code_raises_only_flightkit_errors() -> None:
    offenders: list[str] = []
    for folder in LIBRARY:
        for path in sorted((ROOT / folder).rglob("*.py")):
            hits = bare_raises(path)
            if len(hits) > ALLOWED.get(str(path.relative_to(ROOT)), 0):
                offenders += hits
    assert not offenders, (
        "raise an error of flightkit/errors.py (ConfigError, PlanError, SimError, ...) with what is wrong, "
        "the value and the fix, not a bare ValueError/RuntimeError:\n" + "\n".join(offenders)
    )


def test_the_scan_finds_a_bare_raise(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    src.write_text(
        "def f(x):\n    if x:\n        raise ValueError('no')\n    raise RuntimeError\n"
        "def g():\n    raise ConfigError('a', 'b', 'c', 'd')\n",
        encoding="utf-8",
    )
    assert bare_raises(src, tmp_path) == ["m.py:3: raise ValueError", "m.py:4: raise RuntimeError"]
