"""Saving and loading Gaussian maps: INRIA 3DGS PLY and a full-state .npz, written atomically.

PLY layout (binary little-endian, float32 per property, one vertex per Gaussian), as INRIA's
``GaussianModel.load_ply`` reads it at SH degree 3: ``x y z nx ny nz f_dc_0..2 f_rest_0..44
opacity scale_0..2 rot_0..3`` with opacity as a logit, scales as logs and rot as (w, x, y, z).
Colours are stored as the degree-0 SH coefficient, ``f_dc = (rgb - 0.5) / C0``, and the higher
degrees as zeros. Reading goes through ``plyfile``: ASCII, big-endian and any SH degree load.
"""

from __future__ import annotations

import os
import tempfile

import jax.numpy as jnp
import numpy as np

from splatsearch.gaussians import PARAM_NAMES, GaussianMap, empty_map

SH_C0 = 0.28209479177387814
N_REST = 45  # f_rest_* of SH degree 3: what INRIA's loader asserts
PLY_PROPS = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
             *(f"f_rest_{i}" for i in range(N_REST)), "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3")
NPZ_FORMAT = "splatsearch-gaussian-map"


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux ``/proc``)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)  # elsewhere the only portable read is a set-and-restore
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename.

    The file gets the mode a plain ``open(path, "wb")`` would give it (0666 less the umask),
    not ``mkstemp``'s private 0600, so run folders can be shared as usual.
    """
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=d, prefix=".tmp-", suffix=os.path.splitext(path)[1])
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _active_arrays(gmap: GaussianMap) -> dict[str, np.ndarray]:
    act = np.asarray(gmap.active)
    out = {k: np.asarray(getattr(gmap, k))[act] for k in PARAM_NAMES}
    if gmap.isotropic:
        out["log_scales"] = np.repeat(out["log_scales"].reshape(-1, 1), 3, 1)
    return out


def save_ply(gmap: GaussianMap, path: str) -> int:
    """Write the active Gaussians as an INRIA 3DGS PLY; returns how many were written.

    The layout is exactly what INRIA's ``GaussianModel.load_ply`` and gsplat's tools read at SH
    degree 3: ``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3``, binary
    little-endian float32. Our maps are view-independent, so the 45 ``f_rest`` are zero.
    """
    a = _active_arrays(gmap)
    n = a["means"].shape[0]
    q = a["quats"] / np.maximum(np.linalg.norm(a["quats"], axis=1, keepdims=True), 1e-12)
    cols = [a["means"], np.zeros((n, 3), np.float32), (np.clip(a["colors"], 0, 1) - 0.5) / SH_C0,
            np.zeros((n, N_REST), np.float32), a["opacity_logits"].reshape(n, 1), a["log_scales"], q]
    data = np.concatenate([np.asarray(c, np.float32).reshape(n, -1) for c in cols], 1)
    header = "ply\nformat binary_little_endian 1.0\ncomment splatsearch\nelement vertex %d\n" % n
    header += "".join(f"property float {p}\n" for p in PLY_PROPS) + "end_header\n"
    atomic_write_bytes(path, header.encode("ascii") + data.astype("<f4").tobytes())
    return n


def read_ply_arrays(path: str) -> dict[str, np.ndarray]:
    """The Gaussians of a 3DGS PLY as arrays in rasterizer units.

    Reads ASCII and binary (either endianness) PLY through ``plyfile``. Returns ``means`` (N, 3)
    m, ``quats`` (N, 4) wxyz (as stored), ``scales`` (N, 3) m, ``opacities`` (N,) in [0, 1],
    ``colors`` (N, 3) in [0, 1] (the degree-0 term) and ``sh`` (N, K, 3) all SH coefficients,
    K = (degree + 1)^2, for :func:`splatsearch.rasterization` with ``sh_degree``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a PLY, a truncated body, missing 3DGS properties, a bad ``f_rest``
            count, or NaN / Inf values; the message names the file.
    """
    import plyfile

    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such PLY file: {path}")
    try:
        ply = plyfile.PlyData.read(path)
    except Exception as e:  # plyfile raises its own parse errors, struct errors and EOF on truncation
        if isinstance(e, plyfile.PlyHeaderParseError) or "magic" in str(e):
            raise ValueError(f"{path}: not a PLY file ({e})") from e
        raise ValueError(f"{path}: truncated or malformed PLY body ({type(e).__name__}: {e})") from e
    if "vertex" not in ply:
        raise ValueError(f"{path}: no vertex element")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    missing = [p for p in PLY_PROPS if p not in names and not p.startswith(("n", "f_rest"))]
    if missing:
        raise ValueError(f"{path}: missing 3DGS properties {missing}")
    rest = sorted((k for k in names if k.startswith("f_rest_")), key=lambda k: int(k[7:]))
    n_coef = len(rest) // 3 + 1
    degree = int(round(np.sqrt(n_coef))) - 1
    if len(rest) % 3 or (degree + 1) ** 2 != n_coef:
        raise ValueError(f"{path}: {len(rest)} f_rest properties is not 3 * ((degree + 1)^2 - 1) for any degree")
    get = lambda *ks: np.stack([np.asarray(v[k], np.float32) for k in ks], 1)  # noqa: E731
    dc = get("f_dc_0", "f_dc_1", "f_dc_2")
    sh = np.zeros((len(v), n_coef, 3), np.float32)
    sh[:, 0] = dc
    if rest:  # INRIA stores f_rest channel-major: all coefficients of R, then G, then B
        sh[:, 1:] = get(*rest).reshape(len(v), 3, n_coef - 1).transpose(0, 2, 1)
    out = {"means": get("x", "y", "z"), "quats": get("rot_0", "rot_1", "rot_2", "rot_3"),
           "scales": np.exp(get("scale_0", "scale_1", "scale_2")),
           "opacities": 1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], np.float32))),
           "colors": np.clip(dc * SH_C0 + 0.5, 0, 1), "sh": sh,
           "log_scales": get("scale_0", "scale_1", "scale_2"), "opacity_logits": np.asarray(v["opacity"], np.float32)}
    for k, a in out.items():
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{path}: {k} contains NaN or Inf")
    return out


def load_ply(path: str, capacity: int | None = None) -> GaussianMap:
    """Read a 3DGS PLY (INRIA layout; ASCII or binary, any SH degree) into a map.

    A :class:`GaussianMap` holds view-independent colours, so of the spherical harmonics only the
    degree-0 term is kept; :func:`read_ply_arrays` returns all of them.

    Raises:
        FileNotFoundError / ValueError: as :func:`read_ply_arrays`.
    """
    a = read_ply_arrays(path)
    n = len(a["means"])
    params = {"means": a["means"], "colors": a["colors"], "opacity_logits": a["opacity_logits"],
              "log_scales": a["log_scales"], "quats": a["quats"]}
    return _from_arrays(params, np.ones(n, bool), False, capacity)


def _from_arrays(params: dict, active: np.ndarray, isotropic: bool, capacity: int | None) -> GaussianMap:
    n = int(active.shape[0])
    cap = max(capacity or n, n, 1)
    g = empty_map(cap, isotropic)
    upd = {}
    for k in PARAM_NAMES:
        cur = np.array(getattr(g, k))
        cur[:n] = np.asarray(params[k], np.float32).reshape((n,) + cur.shape[1:])
        upd[k] = jnp.asarray(cur)
    act = np.zeros(cap, bool)
    act[:n] = active
    upd["active"] = jnp.asarray(act)
    return g.replace(**upd)


def save_npz(gmap: GaussianMap, path: str, **extra) -> None:
    """Full state: every slot (capacity), the active mask and the isotropic flag; ``extra``
    arrays (e.g. keyframe poses) are stored under ``extra_<name>``."""
    import io as _io

    arrays = {k: np.asarray(getattr(gmap, k)) for k in PARAM_NAMES}
    arrays["active"] = np.asarray(gmap.active)
    arrays["isotropic"] = np.array(gmap.isotropic)
    arrays["format"] = np.array(NPZ_FORMAT)
    arrays.update({f"extra_{k}": np.asarray(v) for k, v in extra.items()})
    buf = _io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_npz(path: str) -> tuple[GaussianMap, dict]:
    """Read a map written by :func:`save_npz`; returns (map, extra arrays)."""
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise ValueError(f"{path}: not a readable .npz ({type(e).__name__}: {e})") from e
    if str(d.get("format", "")) != NPZ_FORMAT:
        raise ValueError(f"{path}: not a splatsearch Gaussian map")
    missing = [k for k in PARAM_NAMES + ("active", "isotropic") if k not in d]
    if missing:
        raise ValueError(f"{path}: missing arrays {missing}")
    cap = d["means"].shape[0]
    iso = bool(d["isotropic"])
    shapes = {"means": (cap, 3), "log_scales": (cap, 1 if iso else 3), "quats": (cap, 4), "opacity_logits": (cap,),
              "colors": (cap, 3), "active": (cap,)}
    for k, s in shapes.items():
        if d[k].shape != s:
            raise ValueError(f"{path}: {k} has shape {d[k].shape}, expected {s}")
        if k != "active" and not np.all(np.isfinite(d[k])):
            raise ValueError(f"{path}: {k} contains NaN or Inf")
    g = empty_map(cap, iso).replace(**{k: jnp.asarray(d[k]) for k in PARAM_NAMES},
                                    active=jnp.asarray(d["active"].astype(bool)))
    return g, {k[6:]: v for k, v in d.items() if k.startswith("extra_")}
