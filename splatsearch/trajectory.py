"""Camera trajectories: absolute trajectory error (ATE) and TUM-format files.

ATE follows TUM's ``evaluate_ate.py``: the estimated camera positions are rigidly aligned to the
ground truth (rotation + translation, no scale, Horn / Umeyama closed form), and the error is the
RMSE of the remaining position differences. Poses are world-to-camera ``viewmat`` (4, 4) in the
rest of the library; here they are converted to camera-to-world.
"""

from __future__ import annotations

import numpy as np

from splatsearch.io import atomic_write_bytes


def camera_centres(viewmats) -> np.ndarray:
    """(N, 3) float64 camera positions (metres, world frame) of (N, 4, 4) world-to-camera matrices."""
    v = np.asarray(viewmats, np.float64)
    if v.ndim != 3 or v.shape[1:] != (4, 4):
        raise ValueError(f"expected (N, 4, 4) viewmats, got {v.shape}")
    R, t = v[:, :3, :3], v[:, :3, 3]
    return -np.einsum("nji,nj->ni", R, t)  # -R^T t


def umeyama_alignment(src: np.ndarray, dst: np.ndarray, with_scale: bool = False):
    """(R (3, 3), t (3,), s) minimising sum |s R src_i + t - dst_i|^2 over (N, 3) point sets.

    Without scale this is Horn's absolute orientation (what TUM's evaluate_ate uses); the
    reflection case is excluded by the sign correction of Umeyama (1991).
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"expected two (N, 3) point sets, got {src.shape} and {dst.shape}")
    if len(src) < 1:
        raise ValueError("need at least one point to align")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = 1.0
    if with_scale:
        var = (xs ** 2).sum() / len(src)
        s = float(np.trace(np.diag(D) @ S) / var) if var > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def ate(est_viewmats, gt_viewmats, align: bool = True) -> dict:
    """Absolute trajectory error of estimated against ground-truth poses (both (N, 4, 4)
    world-to-camera, same frames). Pairs with a non-finite pose on either side are left out.

    Returns dict: ``rmse``, ``mean``, ``median``, ``max`` (metres), ``n`` (pairs used),
    ``errors`` (per used pair, metres), ``R``, ``t`` (the alignment, estimate to ground truth).
    """
    pe, pg = camera_centres(est_viewmats), camera_centres(gt_viewmats)
    if pe.shape != pg.shape:
        raise ValueError(f"estimated and ground-truth trajectories differ in length: {len(pe)} vs {len(pg)}")
    ok = np.all(np.isfinite(pe), 1) & np.all(np.isfinite(pg), 1)
    if not ok.any():
        raise ValueError("no frame has a finite pose in both trajectories")
    pe, pg = pe[ok], pg[ok]
    R, t = np.eye(3), np.zeros(3)
    if align:
        R, t, _ = umeyama_alignment(pe, pg)
    err = np.linalg.norm(pe @ R.T + t - pg, axis=1)
    return {"rmse": float(np.sqrt(np.mean(err ** 2))), "mean": float(err.mean()), "median": float(np.median(err)),
            "max": float(err.max()), "n": int(ok.sum()), "errors": err, "R": R, "t": t}


def frame_errors(est_viewmats: np.ndarray, gt_viewmats: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0),
                 alignment: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Per-frame errors of estimated against ground-truth poses (both (N, 4, 4) world-to-camera,
    same frames; a frame non-finite on either side gets NaN) after a rigid alignment of the
    estimate: :func:`ate`'s (so the RMS of ``error`` is the ATE) or the given ``alignment``
    (R (3, 3), t (3,)), for instance another trajectory's. Returns dict: ``error`` (N,) m,
    ``offset`` (N, 3) m (aligned estimate minus truth, world frame), ``along`` / ``across`` (N,) m
    (the offset's components along / left of the true camera's viewing direction projected on the
    horizontal, ``up`` being the world's vertical),
    ``yaw`` (N,) rad (the aligned estimate's heading about ``up`` minus the truth's, in (-pi, pi]),
    ``R``, ``t`` the alignment used."""
    est, gt = np.asarray(est_viewmats, np.float64), np.asarray(gt_viewmats, np.float64)
    pe, pg = camera_centres(est), camera_centres(gt)
    if pe.shape != pg.shape:
        raise ValueError(f"estimated and ground-truth trajectories differ in length: {len(pe)} vs {len(pg)}")
    ok = np.all(np.isfinite(pe), 1) & np.all(np.isfinite(pg), 1)  # the others come out NaN
    if alignment is None:
        if not ok.any():
            raise ValueError("no frame has a finite pose in both trajectories")
        R, t, _ = umeyama_alignment(pe[ok], pg[ok])
    else:
        R, t = np.asarray(alignment[0], np.float64), np.asarray(alignment[1], np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    off = pe @ R.T + t - pg

    def forward(c2w_rot):  # the viewing direction (camera +z) projected on the horizontal plane
        f = c2w_rot[:, :, 2] - np.outer(c2w_rot[:, :, 2] @ up, up)
        return f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)

    fg = forward(np.transpose(gt[:, :3, :3], (0, 2, 1)))
    fe = forward(R @ np.transpose(est[:, :3, :3], (0, 2, 1)))
    left = np.cross(up, fg)
    yaw = np.arctan2(np.cross(fg, fe) @ up, np.einsum("ni,ni->n", fg, fe))
    return {"error": np.linalg.norm(off, axis=1), "offset": off, "along": np.einsum("ni,ni->n", off, fg),
            "across": np.einsum("ni,ni->n", off, left), "yaw": yaw, "R": R, "t": t}


def rotation_to_quat(R: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w), w >= 0, of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-12))
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def tum_lines(timestamps, viewmats) -> list[str]:
    """``timestamp tx ty tz qx qy qz qw`` lines (camera-to-world, TUM's groundtruth format) of
    world-to-camera poses; frames with a non-finite pose are left out."""
    ts = np.asarray(timestamps, np.float64)
    vms = np.asarray(viewmats, np.float64)
    if len(ts) != len(vms):
        raise ValueError(f"{len(ts)} timestamps for {len(vms)} poses")
    out = []
    for t, vm in zip(ts, vms):
        if not np.all(np.isfinite(vm)):
            continue
        c2w = np.linalg.inv(vm)
        q = rotation_to_quat(c2w[:3, :3])
        out.append(f"{t:.6f} " + " ".join(f"{v:.6f}" for v in c2w[:3, 3]) + " " + " ".join(f"{v:.6f}" for v in q))
    return out


def write_tum(path: str, timestamps, viewmats) -> int:
    """Write a trajectory in TUM format atomically; returns the number of poses written."""
    lines = tum_lines(timestamps, viewmats)
    atomic_write_bytes(path, ("# timestamp tx ty tz qx qy qz qw (camera-to-world)\n"
                              + "".join(line + "\n" for line in lines)).encode())
    return len(lines)


def read_tum(path: str) -> tuple[np.ndarray, np.ndarray]:
    """((N,) timestamps, (N, 4, 4) world-to-camera) of a TUM-format trajectory file."""
    from splatsearch.datasets.tum import quat_to_R, read_list

    rows = read_list(path)
    ts, vms = [], []
    for t, vals in rows:
        if len(vals) != 7:
            raise ValueError(f"{path}: expected 'timestamp tx ty tz qx qy qz qw' lines, got {len(vals) + 1} values")
        v = np.array([float(x) for x in vals])
        c2w = np.eye(4)
        c2w[:3, :3] = quat_to_R(v[3:])
        c2w[:3, 3] = v[:3]
        ts.append(t)
        vms.append(np.linalg.inv(c2w))
    return np.array(ts), np.array(vms).reshape(-1, 4, 4)
