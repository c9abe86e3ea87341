"""Saving and loading Gaussian maps: INRIA 3DGS PLY and a full-state .npz, written atomically.

PLY layout (binary little-endian, float32 per property, one vertex per Gaussian), as read by
standard 3DGS viewers: ``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2
rot_0 rot_1 rot_2 rot_3`` with opacity as a logit, scales as logs and rot as (w, x, y, z).
Colours are stored as the degree-0 SH coefficient: ``f_dc = (rgb - 0.5) / C0``.
"""

from __future__ import annotations

import os
import tempfile

import jax.numpy as jnp
import numpy as np

from splatsearch.gaussians import PARAM_NAMES, GaussianMap, empty_map

SH_C0 = 0.28209479177387814
PLY_PROPS = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
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
    """Write the active Gaussians as an INRIA 3DGS PLY; returns how many were written."""
    a = _active_arrays(gmap)
    n = a["means"].shape[0]
    q = a["quats"] / np.maximum(np.linalg.norm(a["quats"], axis=1, keepdims=True), 1e-12)
    cols = [a["means"], np.zeros((n, 3), np.float32), (np.clip(a["colors"], 0, 1) - 0.5) / SH_C0,
            a["opacity_logits"].reshape(n, 1), a["log_scales"], q]
    data = np.concatenate([np.asarray(c, np.float32).reshape(n, -1) for c in cols], 1)
    header = "ply\nformat binary_little_endian 1.0\ncomment splatsearch\nelement vertex %d\n" % n
    header += "".join(f"property float {p}\n" for p in PLY_PROPS) + "end_header\n"
    atomic_write_bytes(path, header.encode("ascii") + data.astype("<f4").tobytes())
    return n


def load_ply(path: str, capacity: int | None = None) -> GaussianMap:
    """Read an INRIA-layout 3DGS PLY (extra properties such as f_rest_* are ignored).

    Raises:
        ValueError: not a binary little-endian PLY, missing properties, or a truncated body.
    """
    with open(path, "rb") as f:
        raw = f.read()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary_little_endian PLY is supported")
    n = None
    props: list[tuple[str, str]] = []
    in_vertex = False
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"]:
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n = int(parts[2])
            elif n is not None and props:
                raise ValueError(f"{path}: elements after 'vertex' are not supported")
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list":
                raise ValueError(f"{path}: list properties are not supported")
            props.append((parts[2], parts[1]))
    if n is None:
        raise ValueError(f"{path}: no vertex element")
    sizes = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
             "int": "<i4", "int32": "<i4", "uint": "<u4", "short": "<i2", "ushort": "<u2", "char": "i1"}
    try:
        dtype = np.dtype([(name, sizes[t]) for name, t in props])
    except KeyError as e:
        raise ValueError(f"{path}: unsupported property type {e}") from e
    missing = [p for p in PLY_PROPS if p not in dtype.names and not p.startswith("n")]
    if missing:
        raise ValueError(f"{path}: missing 3DGS properties {missing}")
    body = raw[end + len(b"end_header\n"):]
    if len(body) < n * dtype.itemsize:
        raise ValueError(f"{path}: truncated: {n} vertices need {n * dtype.itemsize} bytes, found {len(body)}")
    v = np.frombuffer(body, dtype=dtype, count=n)
    get = lambda *names: np.stack([v[k].astype(np.float32) for k in names], 1)  # noqa: E731
    params = {
        "means": get("x", "y", "z"), "colors": np.clip(get("f_dc_0", "f_dc_1", "f_dc_2") * SH_C0 + 0.5, 0, 1),
        "opacity_logits": v["opacity"].astype(np.float32), "log_scales": get("scale_0", "scale_1", "scale_2"),
        "quats": get("rot_0", "rot_1", "rot_2", "rot_3"),
    }
    for k, a in params.items():
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{path}: {k} contains NaN or Inf")
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
