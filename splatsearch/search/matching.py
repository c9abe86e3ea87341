"""Feature Extraction Module (FEM, thesis Section 4.2.5): goal image vs novel views (eq 18).

A :class:`Matcher` counts geometrically consistent correspondences between the goal image and
one view; :func:`best_view` takes the argmax over the completed novel views (eq 18) and the object
is declared the goal when ``e_max >= tau_m``.

Offline default :class:`SIFTMatcher`: OpenCV SIFT, Lowe's ratio test (0.75), then the RANSAC
inliers of a fundamental matrix (3 px): the goal image and a view see a 3-D object and its
surroundings from different viewpoints, so true matches lie on several planes, and a homography
keeps only the dominant one.

Thresholds: :data:`DEFAULT_TAU_M` (eq 18's tau_m, on camera-image counts) and
:data:`RENDER_TAU_M` (on counts from rendered views). Rendered views are matched with SIFT's
contrast threshold lowered to :data:`RENDER_CONTRAST_THRESHOLD`, because a render of a Gaussian
map is softer than a camera image and keeps few features at OpenCV's default 0.04; camera images
keep 0.04, where a lower threshold lets other instances match. The measurements behind these
values are in ``docs/results.md``; counts of learned matchers are on another scale and need their
own thresholds.

Real-model adapter :class:`LoFTRMatcher`: kornia's LoFTR with a local checkpoint (the thesis
uses EfficientLoFTR; any detector-free dense matcher fits the same slot), followed by the same
RANSAC verification.
"""

from __future__ import annotations

import copy
import hashlib
import os
from collections.abc import Sequence
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np

#: default feature-match threshold tau_m (RANSAC inliers) for camera images (docs/results.md)
DEFAULT_TAU_M = 15
#: SIFT contrast threshold for rendered novel views (camera images keep OpenCV's 0.04)
RENDER_CONTRAST_THRESHOLD = 0.02
#: match threshold (inliers) for rendered novel views matched with RENDER_CONTRAST_THRESHOLD
RENDER_TAU_M = 15
MODELS = ("homography", "fundamental")


@runtime_checkable
class Matcher(Protocol):
    """Counts correspondences: ``count(goal (H, W, 3), image (H', W', 3)) -> int`` (RGB float in
    [0, 1]; the two sizes may differ)."""

    def count(self, goal: np.ndarray, image: np.ndarray) -> int: ...


class BestView(NamedTuple):
    """Result of :func:`best_view`: ``i_star`` (index of the best view), ``e_max`` (its count)
    and ``counts`` (V,) int per view."""

    i_star: int
    e_max: int
    counts: np.ndarray


def _check_image(name: str, img) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 8 or img.shape[1] < 8:
        raise ValueError(f"{name} must have shape (H, W, 3) with H, W >= 8, got {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{name} contains NaN or Inf")
    return img


def _gray_u8(img: np.ndarray) -> np.ndarray:
    import cv2

    u8 = img if img.dtype == np.uint8 else (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(u8), cv2.COLOR_RGB2GRAY)


def ransac_inliers(pts_a: np.ndarray, pts_b: np.ndarray, model: str = "fundamental", thresh: float = 3.0,
                   min_matches: int = 8) -> int:
    """Number of RANSAC inliers of ``model`` ("homography" or "fundamental") between matched
    pixel coordinates ``pts_a``, ``pts_b`` (M, 2); 0 with fewer than ``min_matches`` matches."""
    import cv2

    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    pa = np.asarray(pts_a, np.float32).reshape(-1, 2)
    pb = np.asarray(pts_b, np.float32).reshape(-1, 2)
    if len(pa) != len(pb):
        raise ValueError(f"point lists differ in length: {len(pa)} vs {len(pb)}")
    if len(pa) < max(int(min_matches), 4 if model == "homography" else 8):
        return 0
    # OpenCV's FM_RANSAC / RANSAC estimators draw from their own fixed-seed RNG, not cv::theRNG(),
    # so the count is reproducible without touching the caller's global OpenCV RNG.
    if model == "homography":
        M, inl = cv2.findHomography(pa, pb, cv2.RANSAC, float(thresh), maxIters=2000, confidence=0.999)
    else:
        M, inl = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, float(thresh), 0.999, 2000)
    if M is None or inl is None:
        return 0
    return int(np.count_nonzero(inl))



def _cached_goal_features(cache: dict, goal: np.ndarray, features):
    """``features(goal)`` through a per-matcher cache of the 8 latest goals, keyed by a hash of
    the image bytes, shape and dtype (the same goal is matched against every novel view)."""
    key = hashlib.blake2b(np.ascontiguousarray(goal).view(np.uint8), digest_size=16).digest() + str(
        (goal.shape, goal.dtype)).encode()
    if key not in cache:
        if len(cache) >= 8:
            cache.pop(next(iter(cache)))
        cache[key] = features(goal)
    return cache[key]

class SIFTMatcher:
    """SIFT + Lowe's ratio test + RANSAC inlier count.

    Args:
        ratio: Lowe's ratio (best / second-best descriptor distance) a match must stay below.
        ransac_thresh: RANSAC reprojection threshold in pixels.
        min_matches: fewer ratio-test matches than this count as 0 (too few to verify).
        model: "fundamental" (default, see the module docstring) or "homography".
        n_features: SIFT keypoint cap (0: no cap).
        contrast_threshold: SIFT's contrast threshold (OpenCV's default 0.04 suits camera
            images; :data:`RENDER_CONTRAST_THRESHOLD` suits the softer renders of a Gaussian map).

    The goal's features are cached per matcher instance (keyed by a hash of the image, the 8
    latest goals), since the same goal is matched against every novel view of every object.
    Counts are reproducible (OpenCV's RANSAC estimators use their own fixed-seed generator) and a
    count neither reseeds nor draws from OpenCV's global RNG.
    """

    def __init__(self, ratio: float = 0.75, ransac_thresh: float = 3.0, min_matches: int = 8,
                 model: str = "fundamental", n_features: int = 0, contrast_threshold: float = 0.04):
        if not 0.0 < ratio < 1.0:
            raise ValueError(f"ratio must be in (0, 1), got {ratio}")
        if not ransac_thresh > 0:
            raise ValueError(f"ransac_thresh must be positive (pixels), got {ransac_thresh}")
        if model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {model!r}")
        if min_matches < 4 or n_features < 0:
            raise ValueError("need min_matches >= 4 and n_features >= 0")
        if not 0.0 < contrast_threshold < 1.0:
            raise ValueError(f"contrast_threshold must be in (0, 1), got {contrast_threshold}")
        self.ratio, self.ransac_thresh, self.min_matches = float(ratio), float(ransac_thresh), int(min_matches)
        self.model, self.n_features, self.contrast_threshold = model, int(n_features), float(contrast_threshold)
        self._sift = None
        self._cache: dict[bytes, tuple] = {}

    @classmethod
    def for_renders(cls, **kwargs) -> SIFTMatcher:
        """A matcher for rendered novel views: :data:`RENDER_CONTRAST_THRESHOLD`, other arguments
        as given (see the module docstring for why renders need a lower contrast threshold)."""
        return cls(contrast_threshold=RENDER_CONTRAST_THRESHOLD, **kwargs)

    def features(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(keypoint pixel coordinates (K, 2), descriptors (K, 128) float32 or None)."""
        import cv2

        if self._sift is None:
            self._sift = cv2.SIFT_create(nfeatures=self.n_features, contrastThreshold=self.contrast_threshold)
        kps, desc = self._sift.detectAndCompute(_gray_u8(img), None)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return pts, desc

    def _goal_features(self, goal: np.ndarray):
        return _cached_goal_features(self._cache, goal, self.features)

    def matches(self, goal: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ratio-test matches as pixel coordinates (pts_goal (M, 2), pts_image (M, 2))."""
        import cv2

        goal, image = _check_image("goal", goal), _check_image("image", image)
        pa, da = self._goal_features(goal)
        pb, db = self.features(image)
        if da is None or db is None or len(da) < 2 or len(db) < 2:
            return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
        good = [m[0] for m in knn if len(m) == 2 and m[0].distance < self.ratio * m[1].distance]
        ia = np.array([g.queryIdx for g in good], int)
        ib = np.array([g.trainIdx for g in good], int)
        return pa[ia].reshape(-1, 2), pb[ib].reshape(-1, 2)

    def count(self, goal: np.ndarray, image: np.ndarray) -> int:
        """RANSAC inliers between ``goal`` and ``image`` (RGB (H, W, 3) float in [0, 1] or uint8)."""
        pa, pb = self.matches(goal, image)
        return ransac_inliers(pa, pb, self.model, self.ransac_thresh, self.min_matches)


def best_view(goal: np.ndarray, images: np.ndarray | Sequence[np.ndarray], matcher: Matcher) -> BestView:
    """Eq 18: ``i* = argmax_i E(I_g, I_i)`` and ``e_max = E(I_g, I_i*)`` over the views.

    goal (H, W, 3); images (V, H', W', 3) or a sequence of (H', W', 3). Ties go to the lowest
    index. Compare ``e_max`` with ``tau_m`` (:data:`DEFAULT_TAU_M`) to declare a match.
    """
    _check_image("goal", goal)
    if len(images) == 0:
        raise ValueError("images must hold at least one view")
    counts = np.array([int(matcher.count(goal, _check_image(f"images[{i}]", im))) for i, im in enumerate(images)],
                      np.int64)
    i = int(np.argmax(counts))
    return BestView(i, int(counts[i]), counts)


def _loftr_default_cfg() -> dict:
    try:
        from kornia.feature.loftr.loftr import default_cfg
    except ImportError:  # moved in some kornia releases
        from kornia.feature.loftr import default_cfg
    return default_cfg


class LoFTRMatcher:
    """LoFTR (kornia) from a local checkpoint, verified with RANSAC like :class:`SIFTMatcher`.

    Args:
        weights_path: local LoFTR checkpoint (a ``torch.save`` dict with ``state_dict``, as the
            official indoor / outdoor checkpoints, or a bare state dict; keys may carry the
            reference implementation's ``matcher.`` prefix).
        conf_thresh: minimum LoFTR match confidence (LoFTR's coarse-level threshold; its own
            default is 0.2).
        max_side: images are resized so the long side is at most this (and to multiples of 8,
            which LoFTR's coarse level needs); coordinates are mapped back to the input pixels.
        ransac_thresh, model, min_matches: the geometric verification (see :func:`ransac_inliers`);
            ``model=None`` counts the confident matches without verification.
        device: torch device string.

    Raises:
        FileNotFoundError: if ``weights_path`` does not exist.
        ImportError: on first use if ``kornia`` / ``torch`` are missing.
    """

    def __init__(self, weights_path: str | os.PathLike, conf_thresh: float = 0.5, max_side: int = 640,
                 ransac_thresh: float = 3.0, model: str | None = "fundamental", min_matches: int = 8,
                 device: str = "cpu"):
        self.weights_path = os.fspath(weights_path)
        if not os.path.isfile(self.weights_path):
            raise FileNotFoundError(f"LoFTR weights not found: {self.weights_path!r} (weights are never downloaded)")
        if not 0.0 <= conf_thresh <= 1.0:
            raise ValueError(f"conf_thresh must be in [0, 1], got {conf_thresh}")
        if model is not None and model not in MODELS:
            raise ValueError(f"model must be one of {MODELS} or None, got {model!r}")
        self.conf_thresh, self.max_side, self.ransac_thresh = float(conf_thresh), int(max_side), float(ransac_thresh)
        self.model, self.min_matches, self.device = model, int(min_matches), device
        self._net = None

    def _load(self):
        if self._net is None:
            try:
                import torch
                from kornia.feature import LoFTR
            except ImportError as e:
                raise ImportError("LoFTRMatcher needs 'kornia' and 'torch' (pip install kornia torch)") from e
            # LoFTR drops coarse matches below its own threshold (0.2 by default) before we see
            # them; make it the caller's conf_thresh so a lower threshold takes effect
            cfg = copy.deepcopy(_loftr_default_cfg())
            cfg["match_coarse"]["thr"] = self.conf_thresh
            net = LoFTR(pretrained=None, config=cfg)
            state = torch.load(self.weights_path, map_location="cpu")
            if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
                state = state["state_dict"]
            # checkpoints of the reference implementation (PyTorch Lightning) prefix every key
            # with "matcher."; kornia's module has no such prefix
            if state and all(k.startswith("matcher.") for k in state):
                state = {k[len("matcher."):]: v for k, v in state.items()}
            net.load_state_dict(state)
            self._net = net.eval().to(self.device)
        return self._net

    def _tensor(self, img: np.ndarray):
        import cv2
        import torch

        g = _gray_u8(img)
        H, W = g.shape
        s = min(1.0, self.max_side / max(H, W))
        h8, w8 = max(8, int(H * s) // 8 * 8), max(8, int(W * s) // 8 * 8)
        g = cv2.resize(g, (w8, h8), interpolation=cv2.INTER_AREA)
        t = torch.from_numpy(g).float().div(255.0)[None, None].to(self.device)
        return t, np.array([W / w8, H / h8], np.float32)

    def count(self, goal: np.ndarray, image: np.ndarray) -> int:
        """Confident LoFTR matches between the two images that survive RANSAC."""
        import torch

        goal, image = _check_image("goal", goal), _check_image("image", image)
        net = self._load()
        t0, s0 = self._tensor(goal)
        t1, s1 = self._tensor(image)
        with torch.inference_mode():
            out = net({"image0": t0, "image1": t1})
        conf = out["confidence"].cpu().numpy()
        keep = conf >= self.conf_thresh
        pa = out["keypoints0"].cpu().numpy()[keep] * s0
        pb = out["keypoints1"].cpu().numpy()[keep] * s1
        if self.model is None:
            return len(pa)
        return ransac_inliers(pa, pb, self.model, self.ransac_thresh, self.min_matches)


# -- matchers that separate the goal on renders (issue 23) ------------------------------------

#: local features :class:`LocalFeatureMatcher` can detect
DETECTORS = ("sift", "rootsift", "akaze")
#: its geometric models: ``essential`` uses the known intrinsics (see ``hfov_deg``)
VERIFY_MODELS = ("fundamental", "homography", "essential", "none")


def rootsift(desc: np.ndarray | None) -> np.ndarray | None:
    """RootSIFT (Arandjelovic & Zisserman 2012): L1-normalise each SIFT descriptor and take the
    element-wise square root, so that L2 distance on the result is the Hellinger kernel.
    desc (K, 128) float32 or None -> same shape / None."""
    if desc is None:
        return None
    d = np.asarray(desc, np.float32)
    return np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-7)).astype(np.float32)


def gms_filter(pts_a: np.ndarray, pts_b: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int],
               grid: int = 12, alpha: float = 4.0) -> np.ndarray:
    """Grid-based motion statistics (GMS, Bian et al. 2017), the single-scale, no-rotation form:
    true matches move together, so a cell of image a whose matches mostly land in one cell of
    image b, with the 8 cells around each agreeing, holds true matches; random ones scatter.

    Each cell of a gets its motion (the cell of b most of its matches land in) and a score (the
    matches of the 3x3 cells around it that follow the same motion); a match is kept when its
    cell scores at least ``alpha * sqrt(mean matches per non-empty cell)`` and it lands within
    one cell of its cell's motion. As in GMS, the grid of a is also tried shifted by half a cell
    in x, y and both, and a match kept on any grid is kept.

    pts_a, pts_b: (M, 2) matched pixel coordinates; size_a, size_b: (H, W) of the two images;
    grid: cells per side. Returns (M,) bool.
    """
    pa = np.asarray(pts_a, np.float64).reshape(-1, 2)
    pb = np.asarray(pts_b, np.float64).reshape(-1, 2)
    if len(pa) != len(pb):
        raise ValueError(f"point lists differ in length: {len(pa)} vs {len(pb)}")
    keep = np.zeros(len(pa), bool)
    if len(pa) == 0:
        return keep
    g = int(grid)
    Hb, Wb = size_b
    bx = np.clip((pb[:, 0] / Wb * g).astype(int), 0, g - 1)
    by = np.clip((pb[:, 1] / Hb * g).astype(int), 0, g - 1)
    cb = by * g + bx
    Ha, Wa = size_a
    for sx, sy in ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)):
        ax = np.clip((pa[:, 0] / Wa * g + sx).astype(int), 0, g)
        ay = np.clip((pa[:, 1] / Ha * g + sy).astype(int), 0, g)
        ga = g + 1  # a shifted grid has one more cell per side
        ca = ay * ga + ax
        pair = np.zeros((ga * ga, g * g), np.int64)
        np.add.at(pair, (ca, cb), 1)
        occupied = np.bincount(ca, minlength=ga * ga)
        thresh = alpha * np.sqrt(max(occupied[occupied > 0].mean(), 1.0))
        motion = pair.argmax(1)
        my, mx = motion // g, motion % g
        score = np.zeros(ga * ga, np.int64)
        for c in np.flatnonzero(occupied):
            cy, cx = divmod(c, ga)
            s = 0
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    y0, x0, y1, x1 = cy + dy, cx + dx, my[c] + dy, mx[c] + dx
                    if 0 <= y0 < ga and 0 <= x0 < ga and 0 <= y1 < g and 0 <= x1 < g:
                        s += pair[y0 * ga + x0, y1 * g + x1]
            score[c] = s
        near = (np.abs(by - my[ca]) <= 1) & (np.abs(bx - mx[ca]) <= 1)
        keep |= (score[ca] >= thresh) & near
    return keep


def _lab(img: np.ndarray) -> np.ndarray:
    import cv2

    u8 = img if img.dtype == np.uint8 else (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    return cv2.cvtColor(np.ascontiguousarray(u8), cv2.COLOR_RGB2LAB).astype(np.float32)


def _patch_colours(img: np.ndarray, pts: np.ndarray, radius: int) -> np.ndarray:
    """Mean CIELAB colour (M, 3) (OpenCV's 8-bit scale) of the (2r+1)^2 patch around each point."""
    import cv2

    lab = cv2.blur(_lab(img), (2 * radius + 1, 2 * radius + 1))
    H, W = lab.shape[:2]
    x = np.clip(np.round(pts[:, 0] - 0.5).astype(int), 0, W - 1)
    y = np.clip(np.round(pts[:, 1] - 0.5).astype(int), 0, H - 1)
    return lab[y, x]


def _akaze_create(threshold: float):
    """AKAZE is in OpenCV's main module up to 4.x and in contrib's ``xfeatures2d`` from 5.0."""
    import cv2

    make = getattr(cv2, "AKAZE_create", None) or getattr(getattr(cv2, "xfeatures2d", None), "AKAZE_create", None)
    if make is None:
        raise ImportError(f"this OpenCV ({cv2.__version__}) has no AKAZE: OpenCV 5 moved it to contrib "
                          "(pip install opencv-contrib-python-headless instead of opencv-python-headless)")
    return make(threshold=threshold)


def _k_for(size: tuple[int, int], hfov_deg: float) -> np.ndarray:
    H, W = size
    f = 0.5 * W / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], np.float64)


class LocalFeatureMatcher:
    """Local features, matching, filters and geometric verification, each a choice, so that the
    variants studied for the NVSM (``docs/matching.md``) are one class.

    Args:
        detector: "sift", "rootsift" (SIFT with RootSIFT descriptors) or "akaze" (binary
            descriptors, Hamming distance).
        ratio: Lowe's ratio test (best / second-best distance); None: no ratio test.
        mutual: keep only mutual nearest neighbours (a's best in b has a as its best in a).
        gms: keep only matches that pass :func:`gms_filter` (``gms_grid``, ``gms_alpha``).
        colour_tol: keep only matches whose patch colours (mean CIELAB over a
            ``colour_radius`` px patch, OpenCV's 8-bit L*a*b* scale) differ by at most this;
            None: no colour check.
        model: RANSAC model: "fundamental", "homography", "essential" (five-point, on points
            normalised with the intrinsics of a pinhole camera with ``hfov_deg`` horizontal
            field of view and a centred principal point, as the simulator's and the NVSM's
            cameras) or "none" / None (count the filtered matches).
        ransac_thresh: RANSAC threshold in pixels (converted to normalised units for "essential").
        min_matches: fewer filtered matches than this count as 0.
        min_inlier_ratio: a count whose inliers are fewer than this fraction of the filtered
            matches is 0 (RANSAC fits some model to any handful of random matches).
        contrast_threshold: SIFT's contrast threshold (:data:`RENDER_CONTRAST_THRESHOLD` for
            renders); akaze_threshold: AKAZE's detector threshold.
        n_features: SIFT keypoint cap (0: none).

    Counts are deterministic (OpenCV's RANSAC estimators use their own fixed-seed generator).
    The goal's features are cached per instance (the 8 latest goal images).
    """

    def __init__(self, detector: str = "rootsift", ratio: float | None = 0.8, mutual: bool = True,
                 gms: bool = False, colour_tol: float | None = None, model: str = "fundamental",
                 ransac_thresh: float = 3.0, min_matches: int = 8, min_inlier_ratio: float = 0.0,
                 contrast_threshold: float = RENDER_CONTRAST_THRESHOLD, akaze_threshold: float = 0.0005,
                 n_features: int = 0, hfov_deg: float = 79.0, colour_radius: int = 3, gms_grid: int = 12,
                 gms_alpha: float = 4.0):
        if detector not in DETECTORS:
            raise ValueError(f"detector must be one of {DETECTORS}, got {detector!r}")
        if ratio is not None and not 0.0 < ratio < 1.0:
            raise ValueError(f"ratio must be in (0, 1) or None, got {ratio}")
        if ratio is None and not mutual:
            raise ValueError("need a ratio test, mutual nearest neighbours, or both (else every feature matches)")
        model = "none" if model is None else model  # a spec's "model=none" arrives as None
        if model not in VERIFY_MODELS:
            raise ValueError(f"model must be one of {VERIFY_MODELS}, got {model!r}")
        if not ransac_thresh > 0:
            raise ValueError(f"ransac_thresh must be positive (pixels), got {ransac_thresh}")
        if min_matches < 5 or n_features < 0:
            raise ValueError(f"need min_matches >= 5 and n_features >= 0, got {min_matches}, {n_features}")
        if not 0.0 <= min_inlier_ratio <= 1.0:
            raise ValueError(f"min_inlier_ratio must be in [0, 1], got {min_inlier_ratio}")
        if colour_tol is not None and not colour_tol > 0:
            raise ValueError(f"colour_tol must be positive or None, got {colour_tol}")
        if not 0.0 < contrast_threshold < 1.0 or not akaze_threshold > 0:
            raise ValueError("need 0 < contrast_threshold < 1 and akaze_threshold > 0")
        if not 0.0 < hfov_deg < 180.0:
            raise ValueError(f"hfov_deg must be in (0, 180), got {hfov_deg}")
        if colour_radius < 0 or gms_grid < 2 or not gms_alpha > 0:
            raise ValueError("need colour_radius >= 0, gms_grid >= 2 and gms_alpha > 0")
        self.detector, self.ratio, self.mutual, self.gms = detector, ratio, bool(mutual), bool(gms)
        self.colour_tol = None if colour_tol is None else float(colour_tol)
        self.model, self.ransac_thresh, self.min_matches = model, float(ransac_thresh), int(min_matches)
        self.min_inlier_ratio = float(min_inlier_ratio)
        self.contrast_threshold, self.akaze_threshold = float(contrast_threshold), float(akaze_threshold)
        self.n_features, self.hfov_deg, self.colour_radius = int(n_features), float(hfov_deg), int(colour_radius)
        self.gms_grid, self.gms_alpha = int(gms_grid), float(gms_alpha)
        self._det = None
        self._cache: dict[bytes, tuple] = {}

    def __repr__(self) -> str:
        keys = ("detector", "ratio", "mutual", "gms", "colour_tol", "model", "ransac_thresh", "min_inlier_ratio")
        return f"LocalFeatureMatcher({', '.join(f'{k}={getattr(self, k)!r}' for k in keys)})"

    def features(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(keypoint pixel coordinates (K, 2), descriptors (K, D) or None)."""
        import cv2

        if self._det is None:
            if self.detector == "akaze":
                self._det = _akaze_create(self.akaze_threshold)
            else:
                self._det = cv2.SIFT_create(nfeatures=self.n_features, contrastThreshold=self.contrast_threshold)
        kps, desc = self._det.detectAndCompute(_gray_u8(img), None)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        if self.detector == "rootsift":
            desc = rootsift(desc)
        return pts, desc

    def _goal_features(self, goal: np.ndarray):
        return _cached_goal_features(self._cache, goal, self.features)

    def matches(self, goal: np.ndarray, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filtered matches as pixel coordinates (pts_goal (M, 2), pts_image (M, 2)): nearest
        neighbours, then the ratio test, mutual check, colour check and GMS that are switched on."""
        import cv2

        goal, image = _check_image("goal", goal), _check_image("image", image)
        pa, da = self._goal_features(goal)
        pb, db = self.features(image)
        none = np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
        if da is None or db is None or len(da) < 2 or len(db) < 2:
            return none
        norm = cv2.NORM_HAMMING if self.detector == "akaze" else cv2.NORM_L2
        bf = cv2.BFMatcher(norm)
        knn = bf.knnMatch(da, db, k=2)
        ia, ib, keep = [], [], []
        for m in knn:
            if not m:
                continue
            ia.append(m[0].queryIdx)
            ib.append(m[0].trainIdx)
            keep.append(self.ratio is None or (len(m) == 2 and m[0].distance < self.ratio * m[1].distance))
        ia, ib, keep = np.asarray(ia, int), np.asarray(ib, int), np.asarray(keep, bool)
        if self.mutual and len(ia):
            back = np.full(len(db), -1, int)
            for m in bf.match(db, da):
                back[m.queryIdx] = m.trainIdx
            keep &= back[ib] == ia
        ia, ib = ia[keep], ib[keep]
        ma, mb = pa[ia].reshape(-1, 2), pb[ib].reshape(-1, 2)
        if self.colour_tol is not None and len(ma):
            ok = np.linalg.norm(_patch_colours(goal, ma, self.colour_radius)
                                - _patch_colours(image, mb, self.colour_radius), axis=1) <= self.colour_tol
            ma, mb = ma[ok], mb[ok]
        if self.gms and len(ma):
            ok = gms_filter(ma, mb, goal.shape[:2], image.shape[:2], self.gms_grid, self.gms_alpha)
            ma, mb = ma[ok], mb[ok]
        return ma, mb

    def inliers(self, pts_a: np.ndarray, pts_b: np.ndarray, size_a: tuple[int, int],
                size_b: tuple[int, int]) -> int:
        """RANSAC inliers of :attr:`model` between matched pixel coordinates of images of sizes
        ``size_a``, ``size_b`` (H, W); the match count itself for ``model="none"``."""
        import cv2

        n = len(pts_a)
        if n < self.min_matches:
            return 0
        if self.model == "none":
            return n
        if self.model != "essential":
            return ransac_inliers(pts_a, pts_b, self.model, self.ransac_thresh, self.min_matches)
        Ka, Kb = _k_for(size_a, self.hfov_deg), _k_for(size_b, self.hfov_deg)
        na = cv2.undistortPoints(np.asarray(pts_a, np.float64).reshape(-1, 1, 2), Ka, None).reshape(-1, 2)
        nb = cv2.undistortPoints(np.asarray(pts_b, np.float64).reshape(-1, 1, 2), Kb, None).reshape(-1, 2)
        f = 0.5 * (Ka[0, 0] + Kb[0, 0])
        # several keypoints at one spot (SIFT's orientations) give repeated matches; a minimal sample
        # of repeats makes the five-point solver's polynomial degenerate, which OpenCV raises on
        _, first = np.unique(np.round(np.hstack([na, nb]), 6), axis=0, return_index=True)
        na, nb = na[np.sort(first)], nb[np.sort(first)]
        if len(na) < self.min_matches:
            return 0
        try:
            E, inl = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.999,
                                          threshold=self.ransac_thresh / f)
        except cv2.error:  # a degenerate sample left (collinear or near-identical points)
            return 0
        if E is None or inl is None:
            return 0
        # several solutions can come back stacked; OpenCV's mask is that of the best one
        return int(np.count_nonzero(inl))

    def count(self, goal: np.ndarray, image: np.ndarray) -> int:
        """Verified correspondences between ``goal`` and ``image`` (RGB (H, W, 3) float in [0, 1]
        or uint8); 0 when the inlier ratio is below ``min_inlier_ratio``."""
        pa, pb = self.matches(goal, image)
        n = self.inliers(pa, pb, np.shape(goal)[:2], np.shape(image)[:2])
        if n and self.min_inlier_ratio > 0 and n < self.min_inlier_ratio * len(pa):
            return 0
        return n


#: named presets of :class:`LocalFeatureMatcher` (spec kinds of :func:`splatsearch.plugins.make_matcher`)
MATCHER_PRESETS: dict[str, dict] = {
    "rootsift": dict(detector="rootsift", ratio=0.8, mutual=True),
    "akaze": dict(detector="akaze", ratio=0.8, mutual=True),
    # the best mean ROC AUC on the dev NVSM views (docs/results.md), within the noise of plain SIFT
    "sift-essential": dict(detector="sift", ratio=0.75, mutual=False, model="essential"),
}


# -- separation of the goal from its look-alikes ----------------------------------------------

def roc_auc(positives: Sequence[float], negatives: Sequence[float]) -> float:
    """Area under the ROC curve of scores that should rank ``positives`` above ``negatives``:
    the probability that a random positive outscores a random negative, ties counting half
    (the Mann-Whitney U statistic over ``len(pos) * len(neg)``). Raises ValueError when either
    list is empty or holds a non-finite score."""
    p = np.asarray(positives, np.float64).ravel()
    n = np.asarray(negatives, np.float64).ravel()
    if len(p) == 0 or len(n) == 0:
        raise ValueError(f"need at least one positive and one negative score, got {len(p)} and {len(n)}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
        raise ValueError("scores must be finite")
    gt = (p[:, None] > n[None, :]).sum()
    eq = (p[:, None] == n[None, :]).sum()
    return float((gt + 0.5 * eq) / (len(p) * len(n)))
