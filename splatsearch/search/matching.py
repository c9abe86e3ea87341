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
        key = hashlib.blake2b(np.ascontiguousarray(goal).view(np.uint8), digest_size=16).digest() + str(
            (goal.shape, goal.dtype)).encode()
        if key not in self._cache:
            if len(self._cache) >= 8:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = self.features(goal)
        return self._cache[key]

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
