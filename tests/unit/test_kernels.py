"""The compiled VO kernels (estimation._kernels) against plain numpy references.

Each reference is the numpy expression the kernel replaced, written out here. The kernels
reproduce its arithmetic operation by operation; on this project's machines the results are
equal bit for bit (the VO trajectories did not move by a bit when the kernels came in), but
numpy's matrix products go through OpenBLAS, whose rounding depends on the CPU's code path,
so the floating-point comparisons here allow a few units in the last place (``same``). Masks
and the flow RANSAC's inlier decisions are compared exactly.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimation import _kernels, _pose_kernel
from estimation._grid_kernel import count_cells
from estimation.camera_geometry import depth_weight
from estimation.features import occupied_cells
from estimation.motion import invert
from estimation.pnp import refine_pose
from flightkit.errors import EstimationError

SIZES = [1, 2, 3, 4, 5, 7, 16, 33, 200, 457]


def same(a: np.ndarray, b: np.ndarray, rtol: float = 1e-12) -> bool:
    """Equal to rounding (and NaN where the other is NaN); float32 to its own precision."""
    a, b = np.asarray(a), np.asarray(b)
    if np.float32 in (a.dtype, b.dtype):
        rtol = max(rtol, 1e-6)
    return a.shape == b.shape and a.dtype == b.dtype and bool(np.allclose(a, b, rtol=rtol, atol=rtol, equal_nan=True))


FX, FY, CX, CY = 262.5, 263.1, 159.7, 119.4


def _pose(rng: np.random.Generator, rot_sigma: float = 0.2, t_sigma: float = 0.1) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(scale=rot_sigma, size=3)).as_matrix()
    T[:3, 3] = rng.normal(scale=t_sigma, size=3)
    return T


def _points(rng: np.random.Generator, n: int, z_lo: float = 0.3) -> np.ndarray:
    return np.asarray(np.c_[rng.uniform(-2.0, 2.0, (n, 2)), rng.uniform(z_lo, 5.0, n)], dtype=np.float64)


def _pixels(rng: np.random.Generator, X: np.ndarray, T: np.ndarray) -> np.ndarray:
    Xc = X @ T[:3, :3].T + T[:3, 3]
    z = np.where(np.abs(Xc[:, 2]) > 1e-3, Xc[:, 2], 1.0)
    uv = np.c_[FX * Xc[:, 0] / z + CX, FY * Xc[:, 1] / z + CY]
    return np.asarray(uv + rng.normal(scale=2.0, size=uv.shape), dtype=np.float64)


@pytest.mark.parametrize("n", SIZES)
def test_transform_equals_numpy_matmul(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(20):
        X = rng.normal(scale=3.0, size=(n, 3))
        T = _pose(rng, 1.0, 2.0)
        assert same(_kernels.transform(X, T), X @ T[:3, :3].T + T[:3, 3])


def _pose_rows_reference(
    X: np.ndarray, T: np.ndarray, uv: np.ndarray, di: np.ndarray, dd: np.ndarray, fb: float, huber: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One Gauss-Newton step's rows (Jacobian, weighted Jacobian, residuals) of refine_pose, as
    its numpy body built them before the loop was compiled."""
    n = len(X)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    if (z <= 1e-6).any():
        return None
    iz = 1.0 / z
    xz, yz = x * iz, y * iz
    zero = np.zeros(n)
    Ju = np.stack([FX * iz, zero, (-FX * xz) * iz, (-FX * xz) * yz, FX * (xz * xz + 1.0), -FX * yz], axis=1)
    Jv = np.stack([zero, FY * iz, (-FY * yz) * iz, -FY * (yz * yz + 1.0), (FY * xz) * yz, FY * xz], axis=1)
    izd, xd, yd = iz[di], x[di], y[di]
    k = fb * izd * izd
    zd = np.zeros(len(di))
    Jd = np.stack([zd, zd, -k, -k * yd, k * xd, zd], axis=1)
    r = np.concatenate([FX * xz + CX - uv[:, 0], FY * yz + CY - uv[:, 1], fb * izd - dd])
    J = np.concatenate([Ju, Jv, Jd])
    w = huber / np.maximum(np.abs(r), huber)
    return J, J * w[:, None], r


def test_refine_pose_takes_no_step_with_a_point_behind_the_camera() -> None:
    rng = np.random.default_rng(7)
    X = _points(rng, 20)
    X[5, 2] = -1.0
    T0 = _pose(rng, 0.01, 0.01)
    K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    T = refine_pose(T0, X, _pixels(rng, X, np.eye(4)), K)
    assert np.array_equal(T, T0) and T is not T0
    X[5, 2] = 1.0  # the same problem with the point in front moves the pose
    assert not np.array_equal(refine_pose(T0, X, _pixels(rng, X, np.eye(4)), K), T0)


def test_refine_pose_starts_from_the_nearest_rotation() -> None:
    """A start whose rotation drifted off SO(3) (chained estimates) is projected back first; the
    steps multiply onto it, so without that the drift would stay in the result and compound."""
    rng = np.random.default_rng(9)
    X = _points(rng, 60)
    T_true = _pose(rng, 0.05, 0.05)
    uv = _pixels(rng, X, T_true)
    K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    T_drifted = T_true.copy()
    T_drifted[:3, :3] = T_true[:3, :3] @ np.diag([1.004, 0.998, 1.001])
    T = refine_pose(T_drifted, X, uv, K, huber_px=1e9, iterations=20)
    R = T[:3, :3]
    assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12 and np.linalg.det(R) > 0
    T_projected = T_drifted.copy()
    T_projected[:3, :3] = cv2.Rodrigues(cv2.Rodrigues(T_drifted[:3, :3])[0])[0]
    assert same(T, refine_pose(T_projected, X, uv, K, huber_px=1e9, iterations=20), rtol=1e-9)


def test_refine_pose_refuses_inputs_the_compiled_loop_cannot_take() -> None:
    rng = np.random.default_rng(8)
    X = _points(rng, 10)
    uv = _pixels(rng, X, np.eye(4))
    K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    with pytest.raises(EstimationError, match="huber_px is 0"):
        refine_pose(np.eye(4), X, uv, K, huber_px=0.0)
    with pytest.raises(EstimationError, match="10 points and 9 pixels"):
        refine_pose(np.eye(4), X, uv[:9], K)
    with pytest.raises(EstimationError, match="and 11 disparities"):
        refine_pose(np.eye(4), X, uv, K, np.ones(11), 26.0)
    with pytest.raises(EstimationError, match="and 9 translation weights"):
        refine_pose(np.eye(4), X, uv, K, translation_weight=np.ones(9))


def test_pose_kernel_reads_empty_arrays_as_none_given() -> None:
    # empty disparities = NaN everywhere, empty translation weights = ones: the same bits
    rng = np.random.default_rng(9)
    X = _points(rng, 60)
    uv = _pixels(rng, X, _pose(rng, 0.05, 0.05))
    T0 = np.eye(4)
    none = np.empty(0)
    args = (FX, FY, CX, CY, 26.0, 1.0, 6, 1e-10, 6)
    filled = _pose_kernel.pose_gauss_newton(X, T0, uv, np.full(60, np.nan), np.ones(60), none, *args)
    empty = _pose_kernel.pose_gauss_newton(X, T0, uv, none, none, none, *args)
    assert np.array_equal(filled, empty) and not np.array_equal(empty, T0)
    half = np.ones(60)
    half[::2] = 0.5  # (and a weight given is read)
    assert not np.array_equal(_pose_kernel.pose_gauss_newton(X, T0, uv, none, half, none, *args), empty)


@pytest.mark.parametrize("n", [4, 5, 16, 200, 457])
@pytest.mark.parametrize("huber", [1.0, 1e9])
def test_refine_pose_equals_numpy_loop(n: int, huber: float) -> None:
    rng = np.random.default_rng(150 + n)
    for trial in range(10):
        X = _points(rng, n)
        T_true = _pose(rng, 0.05, 0.05)
        uv = _pixels(rng, X, T_true)
        di = np.flatnonzero(rng.random(n) < 0.7) if trial % 2 else np.zeros(0, np.intp)
        dd = 26.0 / (X[di] @ T_true[2, :3] + T_true[2, 3]) + rng.normal(scale=0.2, size=len(di))
        T0 = T_true.copy()
        T0[:3, 3] += rng.normal(scale=0.01, size=3)
        # The loop as numpy wrote it: normal equations by BLAS, LAPACK solve, cv2.Rodrigues.
        T_ref = T0.copy()
        for _ in range(4):
            rows = _pose_rows_reference(X, T_ref, uv, di, dd, 26.0, huber)
            assert rows is not None
            J, Jw, r = rows
            xi = -np.linalg.solve(Jw.T @ J, Jw.T @ r)
            dT = np.eye(4)
            dT[:3, :3] = cv2.Rodrigues(xi[3:])[0]
            dT[:3, 3] = xi[:3]
            T_ref = dT @ T_ref
            if float(xi @ xi) < 1e-10:
                break
        K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
        d = np.full(n, np.nan)
        d[di] = dd
        T = refine_pose(T0, X, uv, K, d if len(di) else None, 26.0, huber_px=huber, iterations=4)
        assert same(T, T_ref, rtol=1e-9)  # after Gauss-Newton steps
        if n >= 200:  # enough points that the 2 px noise averages out: it moved towards the truth
            assert np.abs(T[:3, 3] - T_true[:3, 3]).max() < np.abs(T0[:3, 3] - T_true[:3, 3]).max()


@pytest.mark.parametrize("n", SIZES)
@pytest.mark.parametrize("z_min", [1e-6, 1e-9])
def test_reproj_err2_equals_numpy(n: int, z_min: float) -> None:
    rng = np.random.default_rng(200 + n)
    for _ in range(10):
        X = _points(rng, n, z_lo=-0.5)  # some behind the camera
        T = _pose(rng)
        uv = _pixels(rng, X, T)
        Xc = X @ T[:3, :3].T + T[:3, 3]
        z = np.maximum(Xc[:, 2], z_min)
        du = FX * Xc[:, 0] / z + CX - uv[:, 0]
        dv = FY * Xc[:, 1] / z + CY - uv[:, 1]
        ref = np.where(Xc[:, 2] > z_min, du * du + dv * dv, np.inf)
        assert same(_kernels.reproj_err2(X, T, uv, FX, FY, CX, CY, z_min), ref)


@pytest.mark.parametrize("margin", [20.0, 7.5])
@pytest.mark.parametrize("n", SIZES)
def test_project_equals_numpy(n: int, margin: float) -> None:
    rng = np.random.default_rng(300 + n)
    for _ in range(10):
        X = _points(rng, n, z_lo=-0.5)
        T = _pose(rng)
        Xc = X @ T[:3, :3].T + T[:3, 3]
        front = Xc[:, 2] > 0.05
        z = np.where(front, Xc[:, 2], 1.0)
        u = FX * Xc[:, 0] / z + CX
        v = FY * Xc[:, 1] / z + CY
        inside = front & (u > -margin) & (u < 320 + margin) & (v > -margin) & (v < 240 + margin)
        ref = np.empty((n, 2), np.float32)
        ref[:, 0], ref[:, 1] = u, v
        uv, ins = _kernels.project(X, T, FX, FY, CX, CY, 320.0, 240.0, margin)
        assert uv.dtype == np.float32 and same(uv, ref)
        assert np.array_equal(ins, inside)


def _depth_at_reference(depth: np.ndarray, uv: np.ndarray, lo: float, hi: float) -> np.ndarray:
    h, w = depth.shape
    u = np.rint(uv[:, 0]).astype(np.intp)
    v = np.rint(uv[:, 1]).astype(np.intp)
    inside = (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
    z = np.full(len(uv), np.nan)
    flat = depth.reshape(-1)
    at = v[inside] * w + u[inside]
    c = flat.take(at).astype(np.float64)
    up, down, left, right = flat.take(at - w), flat.take(at + w), flat.take(at - 1), flat.take(at + 1)
    nb_max = np.maximum(np.maximum(up, down), np.maximum(left, right)).astype(np.float64)
    nb_min = np.minimum(np.minimum(up, down), np.minimum(left, right)).astype(np.float64)
    good = (c > 0) & (nb_min > 0) & (nb_max - nb_min < 0.03 * c + 0.01) & (c >= lo) & (c <= hi)
    z[np.flatnonzero(inside)[good]] = c[good]
    return z


def test_depth_at_equals_numpy() -> None:
    rng = np.random.default_rng(11)
    h, w = 60, 80
    # Smooth depth with holes (0), NaNs, far and near values and a step edge.
    depth = (1.0 + 0.01 * np.add.outer(np.arange(h), np.arange(w))).astype(np.float32)
    depth[:, 40:] += 1.5
    depth[rng.random((h, w)) < 0.05] = 0.0
    depth[rng.random((h, w)) < 0.02] = np.nan
    depth[:5, :5] = 9.0
    depth[10:12, 10:12] = 0.05
    uv = np.c_[rng.uniform(-3, w + 3, 3000), rng.uniform(-3, h + 3, 3000)]
    uv[:50] = np.round(uv[:50]) + 0.5  # ties: rounded half to even
    z = _kernels.depth_at(depth, uv[:, 0].copy(), uv[:, 1].copy(), 0.1, 6.0)
    ref = _depth_at_reference(depth, uv, 0.1, 6.0)
    assert same(z, ref)
    assert np.isfinite(z).sum() > 1000  # the test exercised the accepting branch too
    # A NaN pixel (numpy's cast would warn) has no depth.
    nan_px = np.array([np.nan, 30.0])
    assert np.isnan(_kernels.depth_at(depth, nan_px, nan_px[::-1].copy(), 0.1, 6.0)).all()


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    x0 = np.c_[rng.normal(scale=0.4, size=(n, 2)), np.ones(n)]
    x1 = x0 + np.c_[rng.normal(scale=0.02, size=(n, 2)), np.zeros(n)]
    return x0, x1


@pytest.mark.parametrize("n", SIZES)
def test_sampson_distance_equals_numpy(n: int) -> None:
    rng = np.random.default_rng(400 + n)
    for _ in range(10):
        T = _pose(rng, 0.05, 0.05)
        R, t = T[:3, :3].copy(), T[:3, 3].copy()
        x0, x1 = _rays(rng, n)
        E = _skew(t) @ R
        Ex0 = x0 @ E.T
        Etx1 = x1 @ E
        e = np.einsum("ni,ni->n", x1, Ex0)
        den = np.maximum(Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2, 1e-300)
        assert same(_kernels.sampson_distance(R, t, x0, x1, 262.0, True), e * (262.0 / np.sqrt(den)))
        assert same(_kernels.sampson_distance(R, t, x0, x1, 262.0, False), 262.0 * np.abs(e) / np.sqrt(den))


def _sampson_jacobian_reference(R: np.ndarray, t: np.ndarray, x0: np.ndarray, x1: np.ndarray, f: float):  # type: ignore[no-untyped-def]
    u0, v0, u1, v1 = x0[:, 0], x0[:, 1], x1[:, 0], x1[:, 1]
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    t0, t1, t2 = t.tolist()
    y0 = r00 * u0 + r01 * v0 + r02
    y1 = r10 * u0 + r11 * v0 + r12
    y2 = r20 * u0 + r21 * v0 + r22
    P0, P1, P2 = t1 * y2 - t2 * y1, t2 * y0 - t0 * y2, t0 * y1 - t1 * y0
    c0, c1, c2 = t2 * v1 - t1, t0 - t2 * u1, t1 * u1 - t0 * v1
    Q0 = r00 * c0 + r10 * c1 + r20 * c2
    Q1 = r01 * c0 + r11 * c1 + r21 * c2
    e = u1 * P0 + v1 * P1 + P2
    den = np.maximum(P0 * P0 + P1 * P1 + Q0 * Q0 + Q1 * Q1, 1e-300)
    inv = f / np.sqrt(den)
    k = e / den
    ty = t0 * y0 + t1 * y1 + t2 * y2
    py = P0 * y0 + P1 * y1
    g = [
        Q0 * (r10 * c2 - r20 * c1) + Q1 * (r11 * c2 - r21 * c1) + ty * P0 - py * t0,
        Q0 * (r20 * c0 - r00 * c2) + Q1 * (r21 * c0 - r01 * c2) + ty * P1 - py * t1,
        Q0 * (r00 * c1 - r10 * c0) + Q1 * (r01 * c1 - r11 * c0) - py * t2,
        Q0 * (r10 - r20 * v1) + Q1 * (r11 - r21 * v1) - P1 * y2,
        Q0 * (r20 * u1 - r00) + Q1 * (r21 * u1 - r01) + P0 * y2,
        Q0 * (r00 * v1 - r10 * u1) + Q1 * (r01 * v1 - r11 * u1) + P1 * y0 - P0 * y1,
    ]
    de = [y1 * c2 - y2 * c1, y2 * c0 - y0 * c2, y0 * c1 - y1 * c0, y1 - y2 * v1, y2 * u1 - y0, y0 * v1 - y1 * u1]
    return e * inv, np.stack([(de[i] - k * g[i]) * inv for i in range(6)], axis=1)


def _sampson_reference(R: np.ndarray, t: np.ndarray, x0: np.ndarray, x1: np.ndarray, f: float) -> np.ndarray:
    E = _skew(t) @ R
    Ex0 = x0 @ E.T
    Etx1 = x1 @ E
    e = np.einsum("ni,ni->n", x1, Ex0)
    den = np.maximum(Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2, 1e-300)
    return np.asarray(e * (f / np.sqrt(den)), dtype=np.float64)


@pytest.mark.parametrize("n", SIZES)
def test_sampson_jacobian_equals_numpy(n: int) -> None:
    rng = np.random.default_rng(500 + n)
    T = _pose(rng, 0.05, 0.05)
    R, t = T[:3, :3].copy(), T[:3, 3].copy()
    x0, x1 = _rays(rng, n)
    r_ref, J_ref = _sampson_jacobian_reference(R, t, x0, x1, 262.0)
    J = np.empty((n, 6))
    r = _kernels.sampson_jacobian(R, t, x0, x1, 262.0, J)
    assert same(r, r_ref)
    assert same(J, J_ref)


def _interaction(x: np.ndarray, y: np.ndarray, Z: np.ndarray) -> np.ndarray:
    n = len(x)
    L = np.zeros((n, 2, 6))
    L[:, 0, 0], L[:, 0, 2], L[:, 0, 3], L[:, 0, 4], L[:, 0, 5] = -1 / Z, x / Z, x * y, -(1 + x * x), y
    L[:, 1, 1], L[:, 1, 2], L[:, 1, 3], L[:, 1, 4], L[:, 1, 5] = -1 / Z, y / Z, 1 + y * y, -x * y, -x
    return L


@pytest.mark.parametrize("n", [3, 8, 60, 200])
def test_flow_hypotheses_match_numpy_scoring(n: int) -> None:
    rng = np.random.default_rng(600 + n)
    x, y, Z = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.4, 0.4, n), rng.uniform(1.0, 4.0, n)
    L = _interaction(x, y, Z)
    twist = np.array([0.2, -0.1, 0.05, 0.1, -0.2, 0.3])
    flow = L @ twist + rng.normal(scale=0.002, size=(n, 2))
    flow[rng.random(n) < 0.2] += rng.normal(scale=0.3, size=2)  # outliers
    thr2 = 0.01**2
    idx = rng.integers(0, n, (64, 3))
    j, count, mask = _kernels.flow_hypotheses(L, flow, idx, 1e-9, thr2)
    # The numpy formulation it replaced: batched normal equations, residual tensor.
    A = L[idx].reshape(64, 6, 6)
    b = flow[idx].reshape(64, 6)
    At = np.swapaxes(A, 1, 2)
    sol = np.linalg.solve(At @ A + 1e-9 * np.eye(6), At @ b[:, :, None])[:, :, 0]
    err = np.einsum("nij,kj->kni", L, sol) - flow[None]
    inl = np.einsum("kni,kni->kn", err, err) < thr2
    counts = inl.sum(axis=1)
    assert j == int(np.argmax(counts)) and count == counts[j]
    assert np.array_equal(mask, inl[j])


def _flow_refit_reference(
    L: np.ndarray, flow: np.ndarray, mask: np.ndarray, thr2: float, robust_iters: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """velocity_ransac's refits as its numpy body wrote them (lstsq, then weighted solves)."""
    n = len(L)
    err = np.zeros((n, 2))
    for _ in range(1 if robust_iters > 0 else 2):
        if np.count_nonzero(mask) < 3:
            return None
        twist = np.linalg.lstsq(L[mask].reshape(-1, 6), flow[mask].reshape(-1), rcond=None)[0]
        err = np.einsum("nij,j->ni", L, twist) - flow
        mask = np.einsum("ni,ni->n", err, err) < thr2
    A, b, s2 = L.reshape(-1, 6), flow.reshape(-1), 0.25 * thr2
    for _ in range(robust_iters):
        e2 = np.einsum("ni,ni->n", err, err)
        w = np.where(e2 < thr2, 1.0 / (1.0 + e2 / s2), 0.0)
        if np.count_nonzero(w) < 3:
            break
        A_w = A * np.repeat(w, 2)[:, None]
        twist = np.linalg.solve(A_w.T @ A, A_w.T @ b)
        err = (A @ twist).reshape(n, 2) - flow
    return twist, np.einsum("ni,ni->n", err, err)


@pytest.mark.parametrize("n", [3, 4, 8, 60, 200])
@pytest.mark.parametrize("robust_iters", [0, 3])
def test_flow_refit_equals_numpy_refits(n: int, robust_iters: int) -> None:
    rng = np.random.default_rng(700 + n)
    for trial in range(10):
        x, y, Z = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.4, 0.4, n), rng.uniform(1.0, 4.0, n)
        L = _interaction(x, y, Z)
        flow = L @ rng.normal(scale=0.2, size=6) + rng.normal(scale=0.004, size=(n, 2))
        flow[rng.random(n) < 0.2] += rng.normal(scale=0.3, size=2)  # outliers
        mask = rng.random(n) < (0.9 if trial % 3 else 0.3)  # a RANSAC answer, some of them too small
        thr2 = 0.01**2
        ref = _flow_refit_reference(L, flow, mask.copy(), thr2, robust_iters)
        ok, twist, e2 = _kernels.flow_refit(L, flow, mask, thr2, robust_iters)
        if ref is None:
            assert not ok and not twist.any()
            continue
        assert ok
        # normal equations here, an SVD (lstsq) there: equal to ~1e-13 on these well-posed fits
        np.testing.assert_allclose(twist, ref[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(e2, ref[1], rtol=1e-6, atol=1e-15)
        assert np.array_equal(e2 < thr2, ref[1] < thr2)


def test_solve6_equals_lapack_to_rounding() -> None:
    rng = np.random.default_rng(9)
    for _ in range(200):
        M = rng.normal(size=(6, 6))
        y = rng.normal(size=6)
        ref = np.linalg.solve(M, y)
        x = y.copy()
        assert _kernels._solve6(M.copy(), x)
        np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-12)
    assert not _kernels._solve6(np.zeros((6, 6)), np.ones(6))


@pytest.mark.parametrize("method", ["rgbd-pnp", "rgbd-essential", "rgbd-kabsch", "stereo", "flow"])
def test_warm_up_runs_each_method_through_its_estimation_path(method: str) -> None:
    from estimation.pipeline import Quality, warm_up

    poses = warm_up(method)
    assert [p.quality for p in poses] == [Quality.INIT] + [Quality.GOOD] * 4
    # The texture moves 2 px a frame at 250 px focal length and ~2 m: 16 mm a frame, 64 mm in all.
    assert float(np.linalg.norm(poses[-1].T_world_camera[:3, 3])) == pytest.approx(0.064, rel=0.1)
    assert _pose_kernel.pose_gauss_newton.signatures and _kernels.project.signatures  # loaded, ready for live frames
    if method != "flow":
        from estimation import p3p

        assert p3p._ransac.signatures  # PnP RANSAC, every keyframe method's fallback, loaded too
    if method == "rgbd-essential":
        from estimation import five_point

        assert five_point._ransac.signatures  # its 5-point RANSAC ran once too
        from estimation import _essential_kernel

        assert _essential_kernel.essential_prior.signatures  # and the prediction's Sampson fit


def _grid_select_numpy(
    pts: np.ndarray, resp: np.ndarray, occupied: np.ndarray, cs: int, ncx: int, b: int, w: int, h: int, budget: int
) -> np.ndarray:
    """GridDetector's corner choice as numpy code (what ``_grid_kernel.grid_select`` replaced)."""
    keep = (pts[:, 0] >= b) & (pts[:, 0] < w - b) & (pts[:, 1] >= b) & (pts[:, 1] < h - b)
    pts, resp = pts[keep], resp[keep]
    if len(pts) == 0:
        return pts
    cell = (pts[:, 1] // cs).astype(np.int32) * ncx + (pts[:, 0] // cs).astype(np.int32)
    free = ~occupied[cell]
    pts, resp, cell = pts[free], resp[free], cell[free]
    if len(pts) == 0:
        return np.empty((0, 2), np.float32)
    per_cell = max(1, int(np.ceil(budget / max(1, int(np.count_nonzero(~occupied))))))
    order = np.lexsort((-resp, cell))
    cell_sorted = cell[order]
    starts = np.r_[0, np.flatnonzero(np.diff(cell_sorted)) + 1]
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    chosen = order[rank < per_cell]
    if len(chosen) > budget:
        chosen = chosen[np.argsort(-resp[chosen], kind="stable")[:budget]]
    return np.ascontiguousarray(pts[chosen])


@pytest.mark.parametrize("budget", [1, 7, 40, 150, 300, 2000])
def test_grid_select_equals_numpy(budget: int) -> None:
    """The same corners in the same order, ties in strength included (FAST scores are integers)."""
    from estimation._grid_kernel import grid_select

    rng = np.random.default_rng(budget)
    w, h, cs, b = 640, 480, 35, 8
    ncx, ncy = (w + cs - 1) // cs, (h + cs - 1) // cs
    for n in (0, 1, 5, 300, 1500):
        pts = np.c_[rng.integers(0, w, n), rng.integers(0, h, n)].astype(np.float32)
        resp = rng.integers(20, 40, n).astype(np.float32)  # many ties
        occupied = rng.random(ncx * ncy) < rng.uniform(0.0, 0.9)
        got = pts[grid_select(pts, resp, occupied, cs, ncx, b, w, h, budget)]
        want = _grid_select_numpy(pts, resp, occupied, cs, ncx, b, w, h, budget)
        assert got.shape == want.shape and np.array_equal(got, want)


def test_min_eigenvalue_at_is_opencvs_shi_tomasi_score() -> None:
    """The score equals ``cv2.cornerMinEigenVal`` (5x5 block, 3x3 Sobel) up to OpenCV's gradient
    scale ``1 / (4 * 5 * 255)`` squared, at every interior pixel of a textured image; 0 at the border."""
    from estimation._grid_kernel import min_eigenvalue_at

    rng = np.random.default_rng(3)
    gray = cv2.GaussianBlur(rng.integers(0, 256, (60, 80)).astype(np.uint8), (5, 5), 1.2)
    ys, xs = np.mgrid[0:60, 0:80]
    pts = np.c_[xs.ravel(), ys.ravel()].astype(np.float32)
    got = min_eigenvalue_at(gray, pts).reshape(60, 80)
    want = cv2.cornerMinEigenVal(gray, 5, ksize=3) * (4 * 5 * 255) ** 2
    inner = (slice(3, -3), slice(3, -3))
    assert np.allclose(got[inner], want[inner], rtol=1e-4, atol=1e-5 * float(want.max()))
    assert float(got[inner].max()) > 0 and np.all(got[:3] == 0) and np.all(got[:, -3:] == 0)


def test_grid_detector_ranks_a_cells_corners_by_the_chosen_score() -> None:
    """``score="shi-tomasi"`` keeps, in each cell, the corners with the highest Shi-Tomasi score
    among FAST's; ``"fast"`` those with the highest FAST response; another name is refused."""
    from estimation._grid_kernel import min_eigenvalue_at
    from estimation.features import GridDetector

    rng = np.random.default_rng(4)
    gray = cv2.GaussianBlur(rng.integers(0, 256, (240, 320)).astype(np.uint8), (3, 3), 0.8)
    kps = cv2.FastFeatureDetector.create(threshold=5, nonmaxSuppression=True).detect(gray, None)
    pts = np.asarray(cv2.KeyPoint.convert(kps), np.float32)
    st = min_eigenvalue_at(gray, pts)
    fast = np.array([k.response for k in kps], np.float32)
    cell = 80
    for score, strength in (("shi-tomasi", st), ("fast", fast)):
        # One corner per cell (12 cells, budget 12): each cell's strongest inside the border.
        det = GridDetector(max_features=12, cell_px=cell, fast_threshold=5, border_px=8, score=score)
        got = det.detect(gray)
        inside = (pts[:, 0] >= 8) & (pts[:, 0] < 312) & (pts[:, 1] >= 8) & (pts[:, 1] < 232)
        cell_of = (pts[:, 1] // cell).astype(int) * 4 + (pts[:, 0] // cell).astype(int)
        for p in got:
            c = int(p[1] // cell) * 4 + int(p[0] // cell)
            here = inside & (cell_of == c)
            assert strength[(pts == p).all(axis=1)][0] == strength[here].max()
        assert len(got) == 12
    st_pick = GridDetector(12, cell, 5, 8, score="shi-tomasi").detect(gray)
    fast_pick = GridDetector(12, cell, 5, 8, score="fast").detect(gray)
    assert not np.array_equal(st_pick, fast_pick)  # the score decides
    with pytest.raises(EstimationError, match="shi-tomasi"):
        GridDetector(score="harris")


@pytest.mark.parametrize("n", [0, 1, 2, 7, 300, 4000])
@pytest.mark.parametrize("spread_px", [640.0, 1e7])
def test_count_cells_equals_the_unique_cells(n: int, spread_px: float) -> None:
    # a spread of 1e7 px spans too many cells for the table: the sorting path
    rng = np.random.default_rng(n)
    px = rng.random((n, 2)) * spread_px - 30.0
    if n > 2:
        px[1, 0], px[2, 1] = np.nan, -np.inf  # non-finite pixels are in no cell
    for cell_px in (32.0, 70.0):
        finite = np.isfinite(px).all(axis=1)
        cells = np.floor(px[finite] / cell_px).astype(np.int64)
        ref = len(np.unique(cells, axis=0)) if len(cells) else 0
        assert count_cells(px, cell_px) == ref
        assert occupied_cells(px.astype(np.float32), cell_px) == len(
            np.unique(np.floor(px[finite].astype(np.float32).astype(np.float64) / cell_px), axis=0)
        )


def test_invert_rigid_equals_the_numpy_inverse() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        T = _pose(rng, rot_sigma=1.0, t_sigma=5.0)
        Rt = T[:3, :3].T
        ref = np.eye(4)
        ref[:3, :3] = Rt
        ref[:3, 3] = -Rt @ T[:3, 3]
        Ti = invert(T)
        assert same(Ti, ref)
        assert np.allclose(Ti @ T, np.eye(4), atol=1e-12)
        assert Ti is not T and not np.shares_memory(Ti, T)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.03, 1.0, 2.7, 3.0, np.pi - 1e-7, np.pi])
def test_rotation_log_and_the_step_helpers_agree_with_rodrigues(angle: float) -> None:
    from estimation._motion_kernel import _log, scaled_step, step_rate

    def rotation_log(R: np.ndarray) -> np.ndarray:
        out = np.empty(3)
        _log(R, False, out)
        return out

    rng = np.random.default_rng(int(angle * 1e3))
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = cv2.Rodrigues(axis * angle)[0]
        w = rotation_log(R)
        if angle < np.pi - 1e-3:
            assert np.allclose(w, axis * angle, rtol=1e-9, atol=1e-15)
        else:  # a half turn's axis has two signs
            assert min(np.abs(w - axis * angle).max(), np.abs(w + axis * angle).max()) < 1e-7
        assert np.allclose(cv2.Rodrigues(w)[0], R, atol=1e-12)
        if 0.03 <= angle <= 3.0:  # (OpenCV's acos is less exact for smaller angles)
            assert np.allclose(w, cv2.Rodrigues(R)[0].ravel(), rtol=1e-10, atol=1e-15)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
        omega, v = step_rate(T, 0.05)
        assert np.allclose(omega, rotation_log(R.T) / 0.05, rtol=1e-12, atol=1e-15)
        assert np.array_equal(v, -T[:3, 3] / 0.05)
        if angle < np.pi - 1e-3:
            assert np.allclose(omega, -axis * angle / 0.05, rtol=1e-9, atol=1e-13)
        half = scaled_step(T, 0.5)
        assert np.allclose(half[:3, :3] @ half[:3, :3], R, atol=1e-12)
        assert np.array_equal(half[:3, 3], T[:3, 3] * 0.5) and np.array_equal(half[3], [0, 0, 0, 1])
        if 0.03 <= angle <= 3.0:
            assert np.allclose(half[:3, :3], cv2.Rodrigues(cv2.Rodrigues(R)[0] * 0.5)[0], atol=1e-14)


@pytest.mark.parametrize("n", [1, 5, 200])
def test_fuse_points_equals_the_numpy_steps(n: int) -> None:
    rng = np.random.default_rng(40 + n)
    X = _points(rng, n + 30)
    w = rng.uniform(0.1, 5.0, n + 30)
    idx = np.sort(rng.choice(n + 30, n, replace=False))
    X_cur = _points(rng, n)
    X_cur[0, 2] = 1e-4  # below the 1e-3 m floor of the weight
    T_ref_cur = _pose(rng)
    # FrontEnd.fuse as numpy wrote it (depth_weight: 1 / max(z, 1e-3) ** 4)
    X_new = X_cur @ T_ref_cur[:3, :3].T + T_ref_cur[:3, 3]
    w_new = 1.0 / np.maximum(X_cur[:, 2], 1e-3) ** 4
    wsum = w[idx] + w_new
    X_ref, w_ref = X.copy(), w.copy()
    X_ref[idx] = (X[idx] * w[idx][:, None] + X_new * w_new[:, None]) / wsum[:, None]
    w_ref[idx] = wsum
    _kernels.fuse_points(X, w, idx, X_cur, depth_weight(X_cur[:, 2]), T_ref_cur)
    assert same(X, X_ref) and same(w, w_ref)
    others = np.setdiff1d(np.arange(n + 30), idx)
    assert np.array_equal(X[others], X_ref[others])
    # a near measurement (z floored at 1e-3 m) outweighs the point; the others average
    assert np.allclose(X[idx[0]], X_new[0]) and (n == 1 or not np.allclose(X[idx[1:]], X_new[1:]))
