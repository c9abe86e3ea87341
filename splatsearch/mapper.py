"""Online RGB-D Gaussian mapper (SplatSearch map generation, thesis Section 4.2.1, eq 3-10).

For every frame with a known (or tracked) pose:

1. render the map at the pose and densify where it is missing or behind (eq 10);
2. every ``keyframe_every``-th frame becomes a keyframe; the window is the current frame plus
   ``window - 1`` keyframes: the latest one and those that see most of the current frame
   (SplaTAM's overlap selection), or simply the latest ones (``window_select="recent"``);
3. run ``iters`` Adam steps on the loss of eq 7-9: a share ``current_frac`` on the current frame
   (its new regions are constrained by nothing else yet), the rest on random window frames;
4. prune Gaussians that became transparent or oversized, compacting the survivors.

The jitted step depends only on the capacity, which grows by doubling, so a whole run compiles
about log2(N) times. The optimiser state is kept across frames and padded or permuted with the
parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax

from splatsearch.camera import pixels_to_world
from splatsearch.gaussians import GaussianMap, append, compact, empty_map, render_args
from splatsearch.kernels.densify import densify
from splatsearch.losses import l1, mapping_loss, psnr, ssim, ssim_stats
from splatsearch.precision import full_precision
from splatsearch.rasterization import rasterize
from splatsearch.rgbd import clean_depth, fill_depth_holes


@dataclass
class MapperConfig:
    """Mapper settings; defaults follow SplaTAM where the issue names them.

    Optimisation: ``iters`` Adam steps per frame over a window of ``window`` keyframes; a frame
    becomes a keyframe every ``keyframe_every`` frames; ``window_select`` picks the window's
    keyframes ("overlap": those that see most of the current frame; "recent": the latest);
    ``current_frac`` of the steps use the current frame, the rest a window keyframe; ``lr`` is
    the Adam learning rate per parameter group (a dict over means, log_scales, quats,
    opacity_logits, colors). Loss (eq 7-9): ``lambda_p`` weighs the photometric term, itself
    ``w_l1`` L1 + (1 - ``w_l1``) (1 - SSIM), and ``lambda_g`` the depth L1 (metres).
    Densification (eq 10): pixels where the silhouette is below ``tau_o`` or the observed depth
    is in front of the rendered one by more than ``k`` times the median depth error get a new
    Gaussian, every ``stride``-th pixel. Pruning: ``prune_opacity`` (opacity below it) and
    ``prune_scale`` (metres; larger Gaussians go). ``isotropic``: one scale per Gaussian.
    ``initial_capacity``: Gaussian slots before the first doubling. ``seed``: the keyframe
    sampling seed.

    ``submap``: optimise only the Gaussians the window's frames can see (their means inside a
    view grown by ``submap_margin`` of the image size on each side), so a step costs what the
    visible part of the map costs, not the whole house.
    ``surface_init``: new Gaussians are flat ellipses in the local surface plane instead of
    spheres (see :func:`splatsearch.kernels.densify.densify`): views far from the training
    cameras (the NVSM's) see closed surfaces instead of stripes.

    Real sensors (see :mod:`splatsearch.rgbd`): ``pixel_scale`` sizes new Gaussians in pixels
    (``stride`` closes the gaps of a strided grid); ``first_iters`` Adam steps for the first
    frame (None: ``iters``), which alone must cover the view before tracking can trust it;
    depth outside [``min_depth``, ``max_depth``] m, and with ``depth_edge_rel`` > 0 at depth
    edges, is untrusted; ``fill_holes`` densifies pixels without depth at the depth of the
    background next to them, so that the colour loss fits them instead of leaving them empty.

    Per-frame parameters, optimised with the map by the same steps (each window frame keeps its
    own Adam state): ``pose_refine`` refines the poses of frames added with ``refine_pose=True``
    (tracked frames; a local bundle adjustment through the rasterizer's viewmat gradient, step
    sizes ``pose_lr_rot`` rad / ``pose_lr_trans`` m, restricted to a ground robot's planar
    motions with ``pose_planar``; ``pose_lr_trans_loose`` m, when set, is the translation step of
    frames added with ``loose=True`` instead: the caller's mark for a pose that no frame-to-frame
    step anchored, which the map may then pull further); ``exposure`` fits an affine colour (gain ``exp(g)``, bias
    ``b``) per frame, applied to the render in the loss (step size ``exposure_lr``): auto-exposure
    of real cameras then no longer bends the map's colours. The first frame's exposure is fixed
    (it sets the colour scale).

    ``refine_lr_final``: :meth:`Mapper.refine` scales every Adam step (the map's and the frames'
    parameters) from 1 down to this fraction, exponentially over its iterations (1: constant), so
    a long refinement settles instead of wandering at a constant step size.
    """

    iters: int = 15
    window: int = 8
    keyframe_every: int = 5
    window_select: str = "overlap"
    current_frac: float = 0.34
    lr: dict = field(default_factory=lambda: {"means": 1e-3, "log_scales": 5e-3, "quats": 1e-3,
                                              "opacity_logits": 5e-2, "colors": 5e-3})
    lambda_p: float = 0.5
    w_l1: float = 0.8
    lambda_g: float = 1.0
    tau_o: float = 0.5
    k: float = 50.0
    stride: int = 3
    prune_opacity: float = 0.005
    prune_scale: float = 0.5
    isotropic: bool = False
    initial_capacity: int = 16384
    seed: int = 0
    submap: bool = True
    submap_margin: float = 0.5
    surface_init: bool = False
    pixel_scale: float = 1.0
    first_iters: int | None = None
    min_depth: float = 0.0
    max_depth: float = float("inf")
    depth_edge_rel: float = 0.0
    fill_holes: bool = False
    pose_refine: bool = False
    pose_lr_rot: float = 2e-4
    pose_lr_trans: float = 2e-4
    pose_lr_trans_loose: float | None = None
    pose_planar: bool = False
    exposure: bool = False
    exposure_lr: float = 2e-3
    refine_lr_final: float = 1.0

    def validate(self) -> None:
        if self.window_select not in ("overlap", "recent"):
            raise ValueError(f"window_select must be 'overlap' or 'recent', got {self.window_select!r}")
        if not 0.0 <= self.current_frac <= 1.0:
            raise ValueError(f"current_frac must be in [0, 1], got {self.current_frac}")
        if self.first_iters is not None and self.first_iters < 0:
            raise ValueError(f"first_iters must be >= 0, got {self.first_iters}")
        if not self.pixel_scale > 0 or not 0 <= self.min_depth < self.max_depth or self.depth_edge_rel < 0:
            raise ValueError("pixel_scale > 0, 0 <= min_depth < max_depth and depth_edge_rel >= 0 are required")
        if not (self.pose_lr_rot > 0 and self.pose_lr_trans > 0 and self.exposure_lr > 0):
            raise ValueError("pose_lr_rot, pose_lr_trans and exposure_lr must be > 0")
        if self.pose_lr_trans_loose is not None and not self.pose_lr_trans_loose > 0:
            raise ValueError(f"pose_lr_trans_loose must be None or > 0, got {self.pose_lr_trans_loose}")
        if not 0 < self.refine_lr_final <= 1:
            raise ValueError(f"refine_lr_final must be in (0, 1], got {self.refine_lr_final}")
        if self.iters < 0 or self.window < 1 or self.keyframe_every < 1 or self.stride < 1:
            raise ValueError("iters >= 0, window >= 1, keyframe_every >= 1 and stride >= 1 are required")
        missing = {"means", "log_scales", "quats", "opacity_logits", "colors"} - set(self.lr)
        if missing:
            raise ValueError(f"lr is missing learning rates for {sorted(missing)}")


@dataclass
class Frame:
    """rgb (H, W, 3) float32 [0, 1]; depth (H, W) float32 metres (0 invalid); viewmat (4, 4)
    world-to-camera, or None for a frame without a known pose (to be tracked).

    Inside a :class:`Mapper`: refine_pose (its pose is refined with the map when
    ``MapperConfig.pose_refine``); tag (the caller's frame id, reported with refined poses);
    fp (8,): per-frame parameters being optimised (a camera-frame se(3) increment not yet folded
    into ``viewmat``, log colour gain, colour bias)."""

    rgb: np.ndarray
    depth: np.ndarray
    viewmat: np.ndarray | None
    refine_pose: bool = False
    tag: int | None = None
    fix_exposure: bool = False
    loose: bool = False
    fp: np.ndarray = field(default_factory=lambda: np.zeros(8, np.float32))

    @property
    def exposure(self) -> tuple[float, float]:
        """(gain, bias) of the frame's fitted affine colour: observed ~ gain * render + bias."""
        return float(np.exp(self.fp[6])), float(self.fp[7])


_ssim_stats_jit = jax.jit(full_precision(ssim_stats))


def render_map(gmap: GaussianMap, viewmat, K, width: int, height: int):
    """(image (H, W, 3), depth D (H, W, 1), alpha (H, W, 1)) of a map."""
    out = rasterize(*gmap.render_args(), viewmat, K, width, height, render_mode="RGB+D")
    return out.image, out.depth, out.alpha


class Mapper:
    """Incremental Gaussian map from posed RGB-D frames.

    Args:
        K: (3, 3) intrinsics in pixels; width, height: image size.
        config: :class:`MapperConfig`.
    """

    def __init__(self, K, width: int, height: int, config: MapperConfig | None = None):
        self.cfg = config or MapperConfig()
        self.cfg.validate()
        self.K = np.asarray(K, np.float32)
        if self.K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {self.K.shape}")
        self.W, self.H = int(width), int(height)
        self.map = empty_map(self.cfg.initial_capacity, self.cfg.isotropic)
        self.tx, self._step, self._step_fp = _optimiser_and_step(self.cfg, self.K, self.W, self.H)
        c = self.cfg
        self._fp_lrs = np.array([c.pose_lr_rot] * 3 + [c.pose_lr_trans] * 3 + [c.exposure_lr] * 2, np.float32)
        self._fp_lrs_loose = self._fp_lrs.copy()
        if c.pose_lr_trans_loose is not None:
            self._fp_lrs_loose[3:6] = c.pose_lr_trans_loose
        self.opt_state = self.tx.init(self.map.params())
        self.keyframes: list[Frame] = []
        self.n_frames = 0
        self.rng = np.random.default_rng(self.cfg.seed)
        self.last_loss = float("nan")

    def _device_frame(self, f: Frame):
        """Device arrays of a frame, with its SSIM target statistics (computed once per frame)."""
        cached = getattr(f, "_dev", None)
        if cached is None:
            rgb = jnp.asarray(f.rgb)
            cached = (rgb, _ssim_stats_jit(rgb), jnp.asarray(f.depth))
            f._dev = cached
        return cached

    # -- public API -----------------------------------------------------------------------------
    def render(self, viewmat):
        """(image, depth D, alpha) of the current map at ``viewmat`` (numpy arrays)."""
        img, dep, alp = render_map(self.map, viewmat, self.K, self.W, self.H)
        return np.asarray(img), np.asarray(dep)[..., 0], np.asarray(alp)[..., 0]

    def update(self, rgb, depth, viewmat, *, refine_pose: bool = False, tag: int | None = None,
               loose: bool = False) -> dict:
        """Add one posed RGB-D frame: densify, optimise over the keyframe window, prune.

        rgb (H, W, 3) float in [0, 1]; depth (H, W) metres, 0 = invalid; viewmat (4, 4)
        world-to-camera. refine_pose: the pose is an estimate (tracking) that
        ``MapperConfig.pose_refine`` may refine, now and while the frame is a keyframe; tag: the
        caller's id of the frame; loose: its translation is refined with ``pose_lr_trans_loose``
        (when set) instead of ``pose_lr_trans``. Returns stats: added, pruned, n_gaussians, loss, viewmat (the
        frame's pose after this update), poses ({tag: viewmat} of the window's tagged frames).
        """
        rgb = np.asarray(rgb, np.float32)
        depth = np.asarray(depth, np.float32)
        viewmat = np.asarray(viewmat, np.float32)
        if rgb.shape != (self.H, self.W, 3) or depth.shape != (self.H, self.W) or viewmat.shape != (4, 4):
            raise ValueError(f"expected rgb ({self.H}, {self.W}, 3), depth ({self.H}, {self.W}) and viewmat (4, 4); "
                             f"got {rgb.shape}, {depth.shape}, {viewmat.shape}")
        for name, a in (("rgb", rgb), ("depth", depth), ("viewmat", viewmat)):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} contains NaN or Inf")
        cfg = self.cfg
        if cfg.min_depth > 0 or np.isfinite(cfg.max_depth) or cfg.depth_edge_rel > 0:
            depth = clean_depth(depth, cfg.min_depth, cfg.max_depth, cfg.depth_edge_rel)
        frame = Frame(rgb, depth, viewmat, refine_pose=bool(refine_pose), tag=tag,
                      fix_exposure=self.n_frames == 0, loose=bool(loose))
        # 1. densify where the map is missing (eq 10)
        if self.map.n_active:
            _, dhat, alpha = self.render(viewmat)
        else:
            dhat, alpha = np.zeros_like(depth), np.zeros_like(depth)
        new = densify(fill_depth_holes(depth) if cfg.fill_holes else depth, alpha, dhat, rgb, viewmat, self.K,
                      tau_o=cfg.tau_o, k=cfg.k, stride=cfg.stride, pixel_scale=cfg.pixel_scale,
                      surface_aligned=cfg.surface_init and not cfg.isotropic)
        new.pop("mask")
        self.map, self.opt_state, _ = append(self.map, self.opt_state, new)
        # 2. keyframes
        window = self._select_window(frame) + [frame]
        if self.n_frames % self.cfg.keyframe_every == 0:
            self.keyframes.append(frame)
        self.n_frames += 1
        # 3. optimise
        dev = [self._device_frame(f) for f in window]
        # A new frame shows regions that no keyframe constrains yet; a uniform pick over the window
        # would give it ~iters/window steps, so a fixed share of the steps goes to it.
        iters = cfg.first_iters if (self.n_frames == 1 and cfg.first_iters is not None) else cfg.iters
        n_cur = int(round(cfg.current_frac * iters))
        picks = [len(dev) - 1] * n_cur + [int(i) for i in self.rng.integers(0, len(dev), iters - n_cur)]
        self.rng.shuffle(picks)
        self._optimise(dev, picks, window)
        # 4. prune
        params, active = self.map.params(), self.map.active
        opac = np.asarray(jax.nn.sigmoid(params["opacity_logits"]))
        big = np.exp(np.asarray(params["log_scales"]).max(1)) > self.cfg.prune_scale
        active_np = np.asarray(active)
        keep = active_np & (opac >= self.cfg.prune_opacity) & ~big
        pruned = int(active_np.sum() - keep.sum())
        if pruned:
            self.map, self.opt_state = compact(self.map, self.opt_state, keep)
        return {"added": int(new["means"].shape[0]), "pruned": pruned, "n_gaussians": self.map.n_active,
                "loss": self.last_loss, "viewmat": frame.viewmat,
                "poses": {f.tag: f.viewmat for f in window if f.tag is not None and f.refine_pose}}

    def refine(self, iters: int) -> float:
        """Run ``iters`` more Adam steps on keyframes drawn uniformly (no densify or prune), e.g.
        to finish a map once all its frames are in. Returns the last loss."""
        if iters < 0:
            raise ValueError(f"iters must be >= 0, got {iters}")
        if not self.keyframes or iters == 0:
            return self.last_loss
        dev = [self._device_frame(f) for f in self.keyframes]
        scales = np.exp(np.linspace(0.0, np.log(self.cfg.refine_lr_final), iters)) \
            if self.cfg.refine_lr_final < 1 else None
        self._optimise(dev, [int(i) for i in self.rng.integers(0, len(dev), iters)], self.keyframes, scales)
        return self.last_loss

    def _optimise(self, dev: list, picks: list[int], frames: list[Frame], scales: np.ndarray | None = None) -> None:
        """Adam steps on the frames ``dev[i] for i in picks`` (``frames[i]`` their Frame: pose,
        per-frame parameters); ``scales`` (len(picks),): each step's size as a fraction of the
        configured learning rates (None: 1).

        With ``submap`` the steps run on the Gaussians that the frames can see (means inside
        one of the views, grown by ``submap_margin`` of the image), gathered into a
        power-of-two capacity. The projection, sort and Adam costs then follow the visible
        part of the map rather than the whole house; Gaussians that no frame sees get no
        gradient anyway, and they no longer drift on stale Adam momentum.
        """
        if not picks:
            return
        loss = jnp.nan
        rows = self._visible_rows([f.viewmat for f in frames]) if self.cfg.submap else None
        if rows is None:
            params, active, opt_state = self.map.params(), self.map.active, self.opt_state
        else:
            params, active, opt_state, cap = _gather_rows(self.map, self.opt_state, rows)
        cfg = self.cfg
        for n, i in enumerate(picks):
            r, s, d = dev[i]
            f = frames[i]
            mask = self._fp_mask(f)
            sc = 1.0 if scales is None else float(scales[n])
            if mask is None:
                params, opt_state, loss = self._step(params, active, opt_state, r, s, d, jnp.asarray(f.viewmat),
                                                     jnp.float32(sc))
                continue
            params, opt_state, loss, g = self._step_fp(params, active, opt_state, jnp.asarray(f.fp), r, s, d,
                                                       jnp.asarray(f.viewmat), jnp.float32(sc))
            _fp_adam(f, np.asarray(g) * mask, (self._fp_lrs_loose if f.loose else self._fp_lrs) * sc)
        for f in frames:  # fold the pose increments into the poses (the Adam moments stay)
            if np.any(f.fp[:6]):
                f.viewmat = np.asarray(_pose_apply(jnp.asarray(f.viewmat), jnp.asarray(f.fp[:6])), np.float32)
                f.fp[:6] = 0.0
        if rows is None:
            self.map, self.opt_state = self.map.with_params(params), opt_state
        else:
            self.map, self.opt_state = _scatter_rows(self.map, self.opt_state, rows, params, opt_state, cap)
        self.last_loss = float(loss)

    def _fp_mask(self, f: Frame) -> np.ndarray | None:
        """Which of the frame's 8 parameters are free (None: none)."""
        pose = self.cfg.pose_refine and f.refine_pose
        expo = self.cfg.exposure and not f.fix_exposure
        if not (pose or expo):
            return None
        return np.array([pose] * 6 + [expo] * 2, np.float32)

    def _visible_rows(self, viewmats: list) -> np.ndarray | None:
        """Rows of active Gaussians whose means fall in one of the views (None: use them all)."""
        n = self.map.n_active  # active Gaussians are compact at the front
        if n == 0:
            return None
        means = np.asarray(self.map.means)[:n]  # slicing the jax array would compile per n
        vis = np.zeros(n, bool)
        m = self.cfg.submap_margin
        K = self.K
        cap = self.map.capacity
        for k, vm in enumerate(viewmats):
            vm = np.asarray(vm, np.float32)
            # the projection of all rows, as always (a BLAS product of a subset can round
            # differently); the tests below only for the rows no earlier view saw
            pc = means @ vm[:3, :3].T + vm[:3, 3]
            idx = None if k == 0 else np.flatnonzero(~vis)
            if idx is not None:
                if len(idx) == 0:
                    break
                if 2 * len(idx) > n:
                    idx = None  # most rows still unseen (the online map of a house): the gather costs more
                else:
                    pc = pc[idx]
            z = pc[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = K[0, 0] * pc[:, 0] / z + K[0, 2]
                v = K[1, 1] * pc[:, 1] / z + K[1, 2]
            hit = (z > 0.01) & (u > -m * self.W) & (u < (1 + m) * self.W) & (v > -m * self.H) & (v < (1 + m) * self.H)
            if idx is None:
                vis |= hit
            else:
                vis[idx[hit]] = True
            if _bucket(int(np.count_nonzero(vis))) >= cap:
                return None  # more views only add rows: the answer is already "the whole map"
        rows = np.nonzero(vis)[0]
        # a submap nearly as big as the map saves nothing and costs the gather and scatter
        if len(rows) == 0 or _bucket(len(rows)) >= cap:
            return None
        return rows

    def _select_window(self, frame: Frame) -> list[Frame]:
        """Up to ``window - 1`` keyframes to optimise with ``frame``.

        "recent" takes the latest keyframes. "overlap" (SplaTAM's choice) takes those that see the
        most of the current frame's back-projected points, so regions revisited after a long
        detour keep being constrained by their old views instead of drifting to fit the new one.
        """
        n = self.cfg.window - 1
        if n <= 0 or not self.keyframes:
            return []
        if self.cfg.window_select == "recent" or len(self.keyframes) <= n:
            return self.keyframes[-n:]
        pts = _backproject(frame.depth, frame.viewmat, self.K, step=8)
        if len(pts) == 0:
            return self.keyframes[-n:]
        score = np.array([_visible_fraction(pts, kf.viewmat, self.K, self.W, self.H) for kf in self.keyframes])
        # the latest keyframe always joins: it shares the most recent optimiser context; ties in
        # overlap go to the more recent keyframe
        idx = np.arange(len(score))
        order = [i for i in np.lexsort((-idx, -score)) if i != len(self.keyframes) - 1 and score[i] > 0]
        chosen = sorted(order[: n - 1] + [len(self.keyframes) - 1])
        return [self.keyframes[i] for i in chosen]

    def evaluate(self, frames, *, exposure: bool = False) -> dict:
        """Mean PSNR (dB, all pixels), ``psnr_valid`` (dB, pixels with valid observed depth: beyond
        the sensor range nothing can be mapped), SSIM and depth L1 (m, valid pixels) over ``frames``.
        exposure: apply each frame's fitted affine colour (:attr:`Frame.exposure`, e.g. the
        keyframes') to the render first."""
        ps, pv, ss, dl = [], [], [], []
        for f in frames:
            img, dep, _ = render_map(self.map, f.viewmat, self.K, self.W, self.H)
            if exposure:
                gain, bias = f.exposure
                img = img * gain + bias
            valid = (np.asarray(f.depth) > 0)[..., None]
            ps.append(float(psnr(img, f.rgb)))
            pv.append(float(psnr(img, f.rgb, valid)))
            ss.append(float(ssim(img, jnp.asarray(f.rgb))))
            dl.append(float(l1(dep, np.asarray(f.depth)[..., None], valid)))
        return {"psnr": float(np.mean(ps)), "psnr_valid": float(np.mean(pv)), "ssim": float(np.mean(ss)),
                "depth_l1": float(np.mean(dl)), "n": len(ps)}


def _bucket(n: int) -> int:
    """Power-of-two capacity (at least 1024) for ``n`` rows, so the step compiles a few times."""
    return max(1024, 1 << int(np.ceil(np.log2(max(n, 1)))))


def _gather_rows(gmap: GaussianMap, opt_state, rows: np.ndarray):
    """(params, active, opt_state, cap) of the Gaussians ``rows``, padded to a bucket capacity."""
    cap_full, n, cap = gmap.capacity, len(rows), _bucket(len(rows))
    idx = np.zeros(cap, np.int64)
    idx[:n] = rows
    active = np.zeros(cap, bool)
    active[:n] = True

    def take(x):
        x = np.asarray(x)
        return jnp.asarray(x[idx]) if x.ndim >= 1 and x.shape[0] == cap_full else x

    params = {k: take(v) for k, v in gmap.params().items()}
    return params, jnp.asarray(active), jax.tree_util.tree_map(take, opt_state), cap


def _scatter_rows(gmap: GaussianMap, opt_state, rows: np.ndarray, sub_params: dict, sub_state, cap: int):
    """Write the optimised rows back into the full map and optimiser state."""
    cap_full, n = gmap.capacity, len(rows)

    def put(full, sub):
        full = np.asarray(full)
        if full.ndim >= 1 and full.shape[0] == cap_full:
            out = full.copy()
            out[rows] = np.asarray(sub)[:n]
            return jnp.asarray(out)
        return sub  # per-optimiser scalars such as Adam's step count

    params = {k: put(v, sub_params[k]) for k, v in gmap.params().items()}
    return gmap.with_params(params), jax.tree_util.tree_map(put, opt_state, sub_state)


# Mappers with the same camera and loss settings share one optimiser and one jitted step, so
# short-lived mappers (the search's object-local maps) do not compile again each time.
_STEPS: dict = {}


def _optimiser_and_step(cfg: MapperConfig, K: np.ndarray, W: int, H: int):
    key = (tuple(sorted(cfg.lr.items())), cfg.lambda_p, cfg.w_l1, cfg.lambda_g, cfg.isotropic,
           np.asarray(K, np.float32).tobytes(), W, H, cfg.pose_planar)
    if key in _STEPS:
        return _STEPS[key]
    tx = optax.multi_transform({k: optax.adam(v) for k, v in cfg.lr.items()}, {k: k for k in cfg.lr})
    Kj, iso = jnp.asarray(K, jnp.float32), cfg.isotropic
    lambda_p, w_l1, lambda_g = cfg.lambda_p, cfg.w_l1, cfg.lambda_g

    def loss_fn(params, active, rgb, stats, depth, viewmat):
        out = rasterize(*render_args(params, active, iso), viewmat, Kj, W, H, render_mode="RGB+D", validate=False)
        return mapping_loss(out.image, out.depth, rgb, depth, lambda_p=lambda_p, w_l1=w_l1, lambda_g=lambda_g,
                            rgb_stats=stats)

    @jax.jit
    @full_precision
    def step(params, active, opt_state, rgb, stats, depth, viewmat, scale):
        """One Adam step with its size scaled by ``scale`` (a traced scalar: no recompile per value)."""
        loss, grads = jax.value_and_grad(loss_fn)(params, active, rgb, stats, depth, viewmat)
        updates, opt_state = tx.update(grads, opt_state, params)
        updates = jax.tree_util.tree_map(lambda u: u * scale, updates)
        return optax.apply_updates(params, updates), opt_state, loss

    planar = cfg.pose_planar

    def loss_fp(params, fp, active, rgb, stats, depth, viewmat):
        vm = _pose_apply(viewmat, fp[:6], planar)
        out = rasterize(*render_args(params, active, iso), vm, Kj, W, H, render_mode="RGB+D", validate=False)
        image = out.image * jnp.exp(fp[6]) + fp[7]
        return mapping_loss(image, out.depth, rgb, depth, lambda_p=lambda_p, w_l1=w_l1, lambda_g=lambda_g,
                            rgb_stats=stats)

    @jax.jit
    @full_precision
    def step_fp(params, active, opt_state, fp, rgb, stats, depth, viewmat, scale):
        """The step of ``step`` that also returns the gradient of the frame's parameters fp (8,)."""
        loss, (grads, g_fp) = jax.value_and_grad(loss_fp, argnums=(0, 1))(params, fp, active, rgb, stats, depth,
                                                                            viewmat)
        updates, opt_state = tx.update(grads, opt_state, params)
        updates = jax.tree_util.tree_map(lambda u: u * scale, updates)
        return optax.apply_updates(params, updates), opt_state, loss, jnp.where(jnp.isfinite(g_fp), g_fp, 0.0)

    if len(_STEPS) > 16:  # many cameras in one process: keep the cache bounded
        _STEPS.pop(next(iter(_STEPS)))
    _STEPS[key] = (tx, step, step_fp)
    return tx, step, step_fp


def _pose_apply(viewmat, xi, planar: bool = False):
    """``exp(xi) @ viewmat`` (see :func:`splatsearch.slam.perturb_viewmat`); with ``planar`` the
    increment is first projected on a ground robot's motions (:func:`splatsearch.slam.planar_basis`)."""
    from splatsearch.slam import perturb_viewmat, planar_basis

    if planar:
        B = planar_basis(viewmat)
        xi = B @ (B.T @ xi)
    return perturb_viewmat(viewmat, xi)


def _fp_adam(f: Frame, g: np.ndarray, lrs: np.ndarray, b1: float = 0.9, b2: float = 0.999,
             eps: float = 1e-8) -> None:
    """One Adam step on a frame's parameters ``f.fp`` (its moments live on the frame)."""
    st = getattr(f, "_fp_adam", None)
    if st is None:
        st = f._fp_adam = [np.zeros(8, np.float32), np.zeros(8, np.float32), 0]
    st[2] += 1
    st[0] = b1 * st[0] + (1 - b1) * g
    st[1] = b2 * st[1] + (1 - b2) * g * g
    mhat, vhat = st[0] / (1 - b1 ** st[2]), st[1] / (1 - b2 ** st[2])
    f.fp = (f.fp - lrs * mhat / (np.sqrt(vhat) + eps) * (g != 0)).astype(np.float32)


def _backproject(depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray, step: int = 8) -> np.ndarray:
    """World points (N, 3) of every ``step``-th pixel with valid depth."""
    v, u = np.mgrid[step // 2:depth.shape[0]:step, step // 2:depth.shape[1]:step]
    z = depth[v, u]
    ok = z > 0
    return pixels_to_world(u[ok], v[ok], z[ok], viewmat, K)


def _visible_fraction(pts: np.ndarray, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> float:
    """Fraction of world points ``pts`` (N, 3) inside a camera's image, in front of it."""
    cam = pts @ viewmat[:3, :3].T.astype(np.float64) + viewmat[:3, 3]
    z = cam[:, 2]
    front = z > 0.05
    zs = np.where(front, z, 1.0)
    u = K[0, 0] * cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * cam[:, 1] / zs + K[1, 2]
    return float(np.mean(front & (u >= 0) & (u < width) & (v >= 0) & (v < height)))


def perturb_viewmat(viewmat, xi):
    """Alias of :func:`splatsearch.slam.perturb_viewmat` (kept for existing callers)."""
    from splatsearch.slam import perturb_viewmat as _perturb

    return _perturb(viewmat, xi)


def track(gmap: GaussianMap, rgb, depth, init_viewmat, K, width: int, height: int, *, iters: int = 40,
          lr: float = 2e-3, sil_thresh: float = 0.99):
    """Refine a pose against the map; returns (viewmat (4, 4), loss). Kept for existing callers:
    :func:`splatsearch.slam.track` is the full interface (status, divergence checks, timing)."""
    from splatsearch.slam import track as _track

    r = _track(gmap, rgb, depth, init_viewmat, K, width, height, iters=iters, lr_rot=lr, lr_trans=lr,
               sil_thresh=sil_thresh)
    return r.viewmat, r.loss
