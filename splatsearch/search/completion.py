"""VCICN: multi-view completion of NVSM renders (the thesis' view-completion network, eq 14-16).

The thesis completes the N_R renders of an object with a multi-view latent diffusion model. A
diffusion model does not train in an hour on two CPU cores, so this is its deterministic
counterpart, trained on the same kind of pairs (local-map renders and the simulator's ground
truth of the same cameras, :mod:`splatsearch.vcicn.data`): a small U-Net applied to every view,
whose bottleneck tokens of *all* views attend to each other (cross-view attention), so a hole in
one view is filled with what another view saw. Each view's relative camera (its pose in the
first view's frame) is embedded and added to its tokens.

Per view the network sees the render with its holes blanked and the hole mask, at a fixed
low resolution (:attr:`VCICNConfig.width` x :attr:`VCICNConfig.height`); it predicts the whole
view, and only the hole pixels are replaced (at full resolution, by the upsampled prediction):
``out = mask * pred + (1 - mask) * render``. Trained with L1 (all pixels and, weighted up, the
holes) + SSIM of the composite (:func:`loss_fn`).

:class:`VCICNInpainter` implements :class:`~splatsearch.search.inpainting.Inpainter`; its weights
come from a ``.npz`` file (:func:`save_weights` / :func:`load_weights`) whose SHA-256 is checked
against a provenance JSON beside it. The package ships trained weights
(``splatsearch/weights/vcicn.npz``, :func:`shipped_weights`).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["VCICNConfig", "VCICNInpainter", "WeightsError", "build_model", "init_params", "prepare_views",
           "relative_cameras", "loss_fn", "image_gradients", "ssim", "save_weights", "load_weights", "shipped_weights",
           "shipped_weights_available"]

#: the shipped weights, as package data
SHIPPED_PACKAGE = "splatsearch.weights"
SHIPPED_NAME = "vcicn.npz"
SHIPPED_PROVENANCE = "vcicn.json"
#: views per forward pass: stacks are padded to this, so one compiled program serves any N_R up to it
MAX_VIEWS = 16
#: input channels per view: RGB with holes blanked, hole mask
IN_CHANNELS = 4
#: relative-camera features: rotation (9), translation (3), "cameras known" flag (1)
CAM_FEATURES = 13


class WeightsError(ValueError):
    """A VCICN weights file that cannot be used: corrupt, truncated, or not the file its
    provenance describes (checksum mismatch)."""


@dataclass(frozen=True)
class VCICNConfig:
    """Architecture of the VCICN.

    Attributes:
        width, height: model resolution in pixels (both divisible by 8); views are resized to it.
        features: channels of the first U-Net level (doubled at 1/2, quadrupled at 1/4 and 1/8).
        heads, blocks: cross-view attention at the 1/8 bottleneck.
    """

    width: int = 64
    height: int = 48
    features: int = 24
    heads: int = 4
    blocks: int = 2

    def __post_init__(self):
        if self.width % 8 or self.height % 8 or self.width < 8 or self.height < 8:
            raise ValueError(f"model width and height must be positive multiples of 8, got {self.width}x{self.height}")
        if self.features < 8 or self.features % 8 or self.heads < 1 or self.blocks < 0 or (4 * self.features) % self.heads:
            raise ValueError(f"invalid VCICNConfig: {self}")


def build_model(cfg: VCICNConfig):
    """The flax module: ``apply(params, x (B, V, h, w, 4), cams (B, V, 13), valid (B, V) bool)
    -> (B, V, h, w, 3)`` predicted RGB in [0, 1]."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    class ConvBlock(nn.Module):
        feat: int

        @nn.compact
        def __call__(self, x):
            x = nn.Conv(self.feat, (3, 3))(x)
            x = nn.gelu(nn.GroupNorm(num_groups=8)(x))
            y = nn.Conv(self.feat, (3, 3))(x)
            return x + nn.gelu(nn.GroupNorm(num_groups=8)(y))

    def down(x):
        return nn.avg_pool(x, (2, 2), (2, 2))

    def up(x):
        n, h, w, c = x.shape
        return jax.image.resize(x, (n, 2 * h, 2 * w, c), "nearest")

    class VCICNNet(nn.Module):
        c: VCICNConfig

        @nn.compact
        def __call__(self, x, cams, valid):
            B, V, H, W, C = x.shape
            f = self.c.features
            h = x.reshape(B * V, H, W, C)
            s0 = ConvBlock(f)(h)
            s1 = ConvBlock(2 * f)(down(s0))
            s2 = ConvBlock(4 * f)(down(s1))
            b = ConvBlock(4 * f)(down(s2))
            hb, wb, D = H // 8, W // 8, 4 * f
            n = hb * wb
            # float32 whatever jax_enable_x64 says: the weights file stores float32
            pos = self.param("pos", lambda k, s: nn.initializers.normal(0.02)(k, s, jnp.float32), (n, D))
            cam = nn.Dense(D)(nn.gelu(nn.Dense(64)(cams)))  # (B, V, D)
            tok = b.reshape(B, V, n, D) + pos[None, None] + cam[:, :, None, :]
            tok = tok.reshape(B, V * n, D)
            keys = jnp.repeat(valid, n, axis=1)  # (B, V * n)
            mask = keys[:, None, None, :]
            for _ in range(self.c.blocks):
                y = nn.LayerNorm()(tok)
                tok = tok + nn.MultiHeadDotProductAttention(num_heads=self.c.heads)(y, y, mask=mask)
                y = nn.LayerNorm()(tok)
                tok = tok + nn.Dense(D)(nn.gelu(nn.Dense(2 * D)(y)))
            b = b + tok.reshape(B * V, hb, wb, D)
            u = ConvBlock(4 * f)(jnp.concatenate([up(b), s2], -1))
            u = ConvBlock(2 * f)(jnp.concatenate([up(u), s1], -1))
            u = ConvBlock(f)(jnp.concatenate([up(u), s0], -1))
            out = nn.sigmoid(nn.Conv(3, (1, 1))(u))
            return out.reshape(B, V, H, W, 3)

    return VCICNNet(cfg)


def init_params(cfg: VCICNConfig, seed: int = 0) -> Any:
    """Fresh parameters of :func:`build_model` (a nested dict of jax arrays)."""
    import jax
    import jax.numpy as jnp

    model = build_model(cfg)
    x = jnp.zeros((1, 2, cfg.height, cfg.width, IN_CHANNELS), jnp.float32)
    # one compiled program rather than an eager op-by-op init (many small compiles)
    return jax.jit(model.init)(jax.random.PRNGKey(seed), x, jnp.zeros((1, 2, CAM_FEATURES), jnp.float32),
                               jnp.ones((1, 2), bool))


# -- inputs -----------------------------------------------------------------------------------

def relative_cameras(viewmats: np.ndarray | None, n: int) -> np.ndarray:
    """(n, 13) camera features: each view's pose in the first view's camera frame (rotation
    row-major, translation in metres) and a 1 flag; all zeros when ``viewmats`` is None (the
    model was trained with cameras dropped now and then, so it works without them)."""
    out = np.zeros((n, CAM_FEATURES), np.float32)
    if viewmats is None:
        return out
    vms = np.asarray(viewmats, np.float64).reshape(-1, 4, 4)
    if len(vms) != n:
        raise ValueError(f"need one viewmat per view: {n} views, {len(vms)} viewmats")
    inv0 = np.linalg.inv(vms[0])
    for i, vm in enumerate(vms):
        T = vm @ inv0  # camera-0 coordinates -> camera-i coordinates
        out[i, :9] = T[:3, :3].ravel()
        out[i, 9:12] = T[:3, 3]
        out[i, 12] = 1.0
    return out


def prepare_views(images: np.ndarray, masks: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Resize views to the model's size: (x (V, h, w, 4) model input, hole (V, h, w) float).

    The small RGB is the mean of the *known* pixels under each small pixel (normalised area
    averaging, so no blanked hole colour leaks in); a small pixel is a hole when less than half
    of its area is known. images (V, H, W, 3) in [0, 1]; masks (V, H, W) bool, True = hole.
    """
    import cv2

    images = np.asarray(images, np.float32)
    known = (~np.asarray(masks, bool)).astype(np.float32)
    V = len(images)
    x = np.zeros((V, height, width, IN_CHANNELS), np.float32)
    hole = np.zeros((V, height, width), np.float32)
    for i in range(V):
        k = cv2.resize(known[i], (width, height), interpolation=cv2.INTER_AREA)
        s = cv2.resize(images[i] * known[i][..., None], (width, height), interpolation=cv2.INTER_AREA)
        rgb = s / np.maximum(k, 1e-6)[..., None]
        h = (k < 0.5).astype(np.float32)
        x[i, ..., :3] = np.clip(rgb, 0, 1) * (1.0 - h)[..., None]
        x[i, ..., 3] = h
        hole[i] = h
    return x, hole


# -- loss -------------------------------------------------------------------------------------

def ssim(a, b, window: int = 7):
    """Mean SSIM of images a, b (..., H, W, 3) in [0, 1] with a ``window`` x ``window`` box filter
    (valid region only); returns (...) per image."""
    import jax
    import jax.numpy as jnp

    lead = a.shape[:-3]
    H, W = a.shape[-3:-1]
    a = a.reshape((-1, H, W, 3))
    b = b.reshape((-1, H, W, 3))

    def blur(x):
        return jax.lax.reduce_window(x, 0.0, jax.lax.add, (1, window, window, 1), (1, 1, 1, 1), "VALID") / window ** 2

    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu_a, mu_b = blur(a), blur(b)
    va = blur(a * a) - mu_a ** 2
    vb = blur(b * b) - mu_b ** 2
    cov = blur(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (va + vb + c2))
    return jnp.mean(s, axis=(1, 2, 3)).reshape(lead)


#: loss weights: L1 over all pixels, extra L1 over the holes, 1 - SSIM of the composite
LOSS_WEIGHTS = (1.0, 2.0, 0.5)


def image_gradients(img):
    """Forward differences of images (..., H, W, C) along x and y: ((..., H, W-1, C), (..., H-1, W, C))."""
    return img[..., :, 1:, :] - img[..., :, :-1, :], img[..., 1:, :, :] - img[..., :-1, :, :]


def loss_fn(pred, x, hole, gt, valid, grad_weight: float = 0.0):
    """Training loss (a scalar) of predictions pred (B, V, h, w, 3) for inputs x (B, V, h, w, 4),
    holes (B, V, h, w), ground truth gt (B, V, h, w, 3), valid (B, V) views.

    ``grad_weight`` > 0 adds that times the L1 distance between the composite's and the ground
    truth's image gradients (forward differences, all pixels of the valid views): an L1 on
    colours alone is met best by a blur, while this term pays for edges and texture in the fill,
    which is what a local-feature matcher needs."""
    import jax.numpy as jnp

    w_all, w_hole, w_ssim = LOSS_WEIGHTS
    vm = valid.astype(jnp.float32)
    hm = hole[..., None]
    comp = hm * pred + (1 - hm) * x[..., :3]
    err = jnp.abs(pred - gt).mean(-1)  # (B, V, h, w)
    nv = jnp.maximum(vm.sum(), 1.0)
    l_all = (err.mean((-1, -2)) * vm).sum() / nv
    l_hole = ((err * hole).sum((-1, -2)) * vm).sum() / jnp.maximum((hole.sum((-1, -2)) * vm).sum(), 1.0)
    l_ssim = ((1.0 - ssim(comp, gt)) * vm).sum() / nv
    loss = w_all * l_all + w_hole * l_hole + w_ssim * l_ssim
    if grad_weight:
        l_grad = 0.0
        for dc, dg in zip(image_gradients(comp), image_gradients(gt)):
            l_grad = l_grad + (jnp.abs(dc - dg).mean((-1, -2, -3)) * vm).sum() / nv
        loss = loss + grad_weight * l_grad
    return loss


# -- weights ----------------------------------------------------------------------------------

def _flatten(tree, prefix=""):
    out = {}
    for k, v in tree.items():
        key = f"{prefix}/{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten(v, key))
        else:
            out[key] = np.asarray(v, np.float32)
    return out


def _unflatten(flat: dict[str, np.ndarray]) -> dict:
    out: dict = {}
    for key, v in flat.items():
        d = out
        parts = key.split("/")
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = v
    return out


def weights_bytes(params: Any, cfg: VCICNConfig, meta: dict | None = None) -> bytes:
    """The ``.npz`` bytes of ``params`` with the architecture (and ``meta``) stored inside."""
    flat = {"p/" + k: v for k, v in _flatten(_to_numpy(params)).items()}
    flat["__config__"] = np.frombuffer(json.dumps(asdict(cfg)).encode(), np.uint8)
    flat["__meta__"] = np.frombuffer(json.dumps(meta or {}).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, **flat)
    return buf.getvalue()


def _to_numpy(tree):
    if isinstance(tree, dict) or hasattr(tree, "items"):
        return {k: _to_numpy(v) for k, v in tree.items()}
    return np.asarray(tree, np.float32)


def save_weights(path: str, params: Any, cfg: VCICNConfig, meta: dict | None = None,
                 provenance: dict | None = None) -> str:
    """Write the weights to ``path`` atomically and, when ``provenance`` is given, the provenance
    JSON beside it (``path`` with ``.json``) with the file's ``sha256`` added. Returns the SHA-256."""
    from splatsearch.io import atomic_write_bytes

    data = weights_bytes(params, cfg, meta)
    digest = hashlib.sha256(data).hexdigest()
    atomic_write_bytes(path, data)
    if provenance is not None:
        prov = dict(provenance, sha256=digest, bytes=len(data), config=asdict(cfg))
        atomic_write_bytes(os.path.splitext(path)[0] + ".json", json.dumps(prov, indent=1).encode())
    return digest


def _parse_weights(data: bytes, name: str) -> tuple[dict, VCICNConfig, dict]:
    try:
        with np.load(io.BytesIO(data)) as z:
            flat = {k: z[k] for k in z.files}
        cfg = VCICNConfig(**json.loads(bytes(flat.pop("__config__")).decode()))
        meta = json.loads(bytes(flat.pop("__meta__", np.zeros(0, np.uint8))).decode() or "{}")
    except Exception as e:  # noqa: BLE001 - zip, zlib, json and key errors all mean the same here
        raise WeightsError(f"VCICN weights {name} are corrupt or truncated ({type(e).__name__}: {e}); "
                           "reinstall the package or retrain with `splatsearch vcicn train`") from e
    params = _unflatten({k[2:]: v for k, v in flat.items() if k.startswith("p/")})
    ref = _shape_table(cfg)
    got = _flatten(params)
    if set(ref) != set(got) or any(ref[k] != got[k].shape for k in ref):
        raise WeightsError(f"VCICN weights {name} do not fit the architecture they declare ({cfg})")
    return params, cfg, meta


def _shapes(cfg: VCICNConfig):
    import jax

    shapes = jax.eval_shape(lambda: init_params(cfg))
    return jax.tree_util.tree_map(lambda s: np.zeros(s.shape, np.float32), shapes)


@functools.lru_cache(maxsize=8)
def _shape_table(cfg: VCICNConfig) -> dict[str, tuple]:
    """{flattened parameter name: shape} of the architecture ``cfg``. Cached per process: tracing
    the model's init took about 0.4 s of every episode's agent construction."""
    return {k: v.shape for k, v in _flatten(_to_numpy(_shapes(cfg))).items()}


def load_weights(path: str, sha256: str | None = None) -> tuple[dict, VCICNConfig, dict]:
    """Read weights: (params, config, meta). The file's SHA-256 must equal ``sha256`` when given,
    or else the ``sha256`` of a provenance JSON beside it (``path`` with ``.json``) when one
    exists. Raises FileNotFoundError, or :class:`WeightsError` for a corrupt, truncated or
    mismatched file."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"VCICN weights not found: {path!r} (weights are read from local files only)")
    with open(path, "rb") as f:
        data = f.read()
    if sha256 is None:
        prov = os.path.splitext(path)[0] + ".json"
        if os.path.isfile(prov):
            with open(prov) as f:
                try:
                    sha256 = json.load(f).get("sha256")
                except json.JSONDecodeError as e:
                    raise WeightsError(f"provenance file {prov!r} is not valid JSON: {e}") from e
    _check_digest(data, sha256, path)
    return _parse_weights(data, repr(path))


def _check_digest(data: bytes, sha256: str | None, name: str) -> None:
    if sha256 is not None:
        got = hashlib.sha256(data).hexdigest()
        if got != sha256:
            raise WeightsError(f"VCICN weights {name!r} fail their checksum (sha256 {got[:12]}..., expected "
                               f"{sha256[:12]}...): the file is corrupt or not the one its provenance describes")


def shipped_weights_available() -> bool:
    """Whether the package ships VCICN weights (checks presence only, loads nothing)."""
    from importlib import resources

    try:
        return resources.files(SHIPPED_PACKAGE).joinpath(SHIPPED_NAME).is_file()
    except (ModuleNotFoundError, FileNotFoundError):
        return False


def shipped_weights() -> tuple[dict, VCICNConfig, dict, dict]:
    """The weights shipped as package data, read through :mod:`importlib.resources` and checked
    against the shipped provenance: (params, config, meta, provenance). Raises
    FileNotFoundError when the package ships none, :class:`WeightsError` when they fail the check."""
    from importlib import resources

    root = resources.files(SHIPPED_PACKAGE)
    wfile, pfile = root.joinpath(SHIPPED_NAME), root.joinpath(SHIPPED_PROVENANCE)
    if not wfile.is_file():
        raise FileNotFoundError(f"this installation ships no VCICN weights ({SHIPPED_PACKAGE}/{SHIPPED_NAME})")
    if not pfile.is_file():
        raise WeightsError(f"the shipped VCICN weights have no provenance file ({SHIPPED_PACKAGE}/{SHIPPED_PROVENANCE})")
    prov = json.loads(pfile.read_text())
    data = wfile.read_bytes()
    _check_digest(data, prov.get("sha256") or "missing", f"{SHIPPED_PACKAGE}/{SHIPPED_NAME}")
    params, cfg, meta = _parse_weights(data, f"{SHIPPED_PACKAGE}/{SHIPPED_NAME}")
    return params, cfg, meta, prov


# -- inference --------------------------------------------------------------------------------

#: (config, weights digest) -> the jitted forward of :meth:`VCICNInpainter.predict`
_COMPILED: dict = {}


def _params_digest(params: Any) -> str:
    """SHA-256 of a parameter tree's names, shapes and values (float32 bytes)."""
    h = hashlib.sha256()
    for k, v in sorted(_flatten(_to_numpy(params)).items()):
        h.update(k.encode())
        h.update(str(v.shape).encode())
        h.update(np.ascontiguousarray(v, np.float32).tobytes())
    return h.hexdigest()


class VCICNInpainter:
    """The VCICN as an :class:`~splatsearch.search.inpainting.Inpainter`.

    Args:
        weights: a weights ``.npz`` (checked against the provenance JSON beside it when there is
            one); None: the weights shipped with the package.
        sha256: expected SHA-256 of ``weights`` (overrides the provenance file).
        composite: how the prediction enters the output. ``"holes"`` (default): only the hole
            pixels are replaced, ``out = mask * pred + (1 - mask) * render``. ``"over"``: the
            render, which the rasterizer composited over black, is composited over the
            prediction instead, ``out = render + (1 - alpha) * pred`` outside the holes (holes
            as with ``"holes"``), so the soft pixels at the edge of what the map covers
            (opacity between the hole threshold and 1, darkened towards black in the render)
            get the predicted background behind them. Needs the renders' ``alpha``; without it
            ``"over"`` acts as ``"holes"``.

    ``inpaint(images (V, H, W, 3), masks (V, H, W) bool, viewmats=None, alpha=None)`` completes
    all V views jointly: up to :data:`MAX_VIEWS` per forward pass (more are completed in chunks).
    With ``viewmats`` (V, 4, 4) world-to-camera, the views' relative cameras inform the
    attention; the NVSM passes them (:attr:`wants_cameras`). ``alpha`` (V, H, W) in [0, 1] is the
    renders' accumulated opacity (used by ``composite="over"`` only; the NVSM passes it,
    :attr:`wants_alpha`). With ``"holes"``, known
    pixels are returned unchanged and a view without holes is returned as it is. The weights are
    checked when the inpainter is built and moved to JAX on first use.
    """

    #: the NVSM passes viewmats and the full hole masks (background included) to this inpainter
    wants_cameras = True
    completes_background = True
    #: the NVSM passes the renders' opacity too (used by ``composite="over"``)
    wants_alpha = True

    #: the ways :meth:`inpaint` can put the prediction into the render (see the class docstring)
    COMPOSITES = ("holes", "over")

    def __init__(self, weights: str | os.PathLike | None = None, sha256: str | None = None,
                 composite: str = "holes"):
        if composite not in self.COMPOSITES:
            raise ValueError(f"composite must be one of {self.COMPOSITES}, got {composite!r}")
        self.composite = composite
        if weights is None:
            params, cfg, meta, prov = shipped_weights()
            self.source = f"{SHIPPED_PACKAGE}/{SHIPPED_NAME}"
            self.provenance = prov
        else:
            params, cfg, meta = load_weights(os.fspath(weights), sha256)
            self.source = os.fspath(weights)
            self.provenance = None
        self.config, self.meta = cfg, meta
        self._np_params = params
        self._fn = None

    def _compiled(self):
        if self._fn is None:
            # one jitted function per process and set of weights: a new inpainter (every episode
            # builds one) then reuses the compiled program instead of tracing and compiling it
            # again (about 0.35 s a time); the same closure, so the same program and results
            key = (self.config, _params_digest(self._np_params))
            fn = _COMPILED.get(key)
            if fn is None:
                import jax
                import jax.numpy as jnp

                params = jax.tree_util.tree_map(jnp.asarray, self._np_params)
                model = build_model(self.config)
                fn = jax.jit(lambda x, c, v: model.apply(params, x, c, v))
                if len(_COMPILED) >= 4:  # a few weight sets at most (tests, comparisons)
                    _COMPILED.pop(next(iter(_COMPILED)))
                _COMPILED[key] = fn
            self._fn = fn
        return self._fn

    def predict(self, images: np.ndarray, masks: np.ndarray, viewmats: np.ndarray | None = None) -> np.ndarray:
        """The model's prediction of every view at the model's resolution: (V, h, w, 3)."""
        fn = self._compiled()
        cfg = self.config
        x, _hole = prepare_views(images, masks, cfg.width, cfg.height)
        cams = relative_cameras(viewmats, len(x))
        V = len(x)
        out = np.zeros((V, cfg.height, cfg.width, 3), np.float32)
        for s in range(0, V, MAX_VIEWS):
            n = min(MAX_VIEWS, V - s)
            xb = np.zeros((1, MAX_VIEWS) + x.shape[1:], np.float32)
            cb = np.zeros((1, MAX_VIEWS, CAM_FEATURES), np.float32)
            vb = np.zeros((1, MAX_VIEWS), bool)
            xb[0, :n], vb[0, :n] = x[s:s + n], True
            # each chunk's cameras relative to its own first view, as in training
            cb[0, :n] = relative_cameras(None if viewmats is None else np.asarray(viewmats)[s:s + n], n) \
                if s else cams[:n]
            out[s:s + n] = np.asarray(fn(xb, cb, vb))[0, :n]
        return out

    def inpaint(self, images: np.ndarray, masks: np.ndarray, viewmats: np.ndarray | None = None,
                alpha: np.ndarray | None = None) -> np.ndarray:
        """(V, H, W, 3) float32: the hole pixels replaced by the upsampled prediction (and, with
        ``composite="over"`` and ``alpha`` (V, H, W) given, the soft covered pixels composited
        over it)."""
        import cv2

        from .inpainting import _check_stack

        images, masks = _check_stack(images, masks)
        over = self.composite == "over" and alpha is not None
        if over:
            alpha = np.clip(np.asarray(alpha, np.float32).reshape(masks.shape), 0.0, 1.0)
        out = images.copy()
        todo = [i for i in range(len(images)) if masks[i].any() or (over and (alpha[i] < 1.0).any())]
        if not todo:
            return out
        pred = self.predict(images, masks, viewmats)
        H, W = masks.shape[1:]
        for i in todo:
            full = np.clip(cv2.resize(pred[i], (W, H), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
            if over:
                soft = ~masks[i] & (alpha[i] < 1.0)
                out[i][soft] = np.clip(images[i][soft] + (1.0 - alpha[i][soft])[:, None] * full[soft], 0.0, 1.0)
            out[i][masks[i]] = full[masks[i]]
        return out
