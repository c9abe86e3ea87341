"""Instance appearance: how much a detected object looks like the goal object.

The FEM (eq 18) counts local feature matches, which needs texture seen at a similar scale. A
detection far across a room, or an object whose texture is a fine procedural pattern, gives a
handful of matches whichever instance it is. The colours of the object itself tell instances of
one class apart from any distance: every instance has its own materials. This module compares the
goal object's pixels (the detector run on the goal image) with each detection's pixels.

A single view can mislead (another instance may share the goal's colours from one side), so the
agent averages the similarity over several viewpoints, weighted by mask size; the measurements
behind its threshold are in ``docs/results.md``.

A learned embedding plugs in through :class:`AppearanceModel`; :class:`EncoderAppearance` wraps
any :class:`~splatsearch.nav.encoders.ImageEncoder` (e.g. the OpenCLIP or transformers adapters,
which load weights from a local path) over the masked object crop.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol, runtime_checkable

import cv2
import numpy as np


@runtime_checkable
class AppearanceModel(Protocol):
    """Masked-region appearance signatures.

    ``signature(rgb, mask)``: rgb (H, W, 3) float in [0, 1], mask (H, W) bool -> a 1-D signature.
    ``similarity(a, b)``: two signatures -> float in [0, 1] (1: the same appearance).
    """

    def signature(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray: ...

    def similarity(self, a: np.ndarray, b: np.ndarray) -> float: ...


class ColorHistogramAppearance:
    """Hue-saturation histogram of the masked pixels, compared by histogram intersection.

    Hue and saturation change little with the shading of a surface, unlike brightness, so the
    histogram leaves value out. Args: bins (hue, saturation) counts.
    """

    def __init__(self, bins: tuple[int, int] = (18, 4)):
        if len(bins) != 2 or min(bins) < 1:
            raise ValueError(f"bins must be two counts >= 1, got {bins}")
        self.bins = (int(bins[0]), int(bins[1]))

    def signature(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(bins[0] * bins[1],) float32 histogram summing to 1 (all zeros for an empty mask)."""
        rgb = np.asarray(rgb)
        mask = np.asarray(mask)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
        if mask.shape != rgb.shape[:2]:
            raise ValueError(f"mask shape {mask.shape} does not match rgb {rgb.shape[:2]}")
        img = rgb if rgb.dtype == np.uint8 else (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        hsv = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2HSV)
        h = cv2.calcHist([hsv], [0, 1], mask.astype(np.uint8), list(self.bins), [0, 180, 0, 256]).ravel()
        s = float(h.sum())
        return (h / s if s > 0 else h).astype(np.float32)

    def similarity(self, a: np.ndarray, b: np.ndarray) -> float:
        """Histogram intersection in [0, 1]."""
        a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
        if a.shape != b.shape:
            raise ValueError(f"signature shapes differ: {a.shape} vs {b.shape}")
        return float(np.minimum(a, b).sum())


class EncoderAppearance:
    """An :class:`~splatsearch.nav.encoders.ImageEncoder` over the object alone: the mask's bounding
    box with everything outside the mask set to mid-grey, embedded; similarity is the cosine
    mapped to [0, 1]. Args: encoder (``embed(rgb) -> (D,)``), min_size: the crop is padded to at
    least this many pixels a side (encoders want more than a sliver)."""

    def __init__(self, encoder, min_size: int = 32):
        if not hasattr(encoder, "embed"):
            raise TypeError("encoder must have an embed(rgb) method (an ImageEncoder)")
        self.encoder, self.min_size = encoder, int(min_size)

    def signature(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The encoder's embedding (D,) of the masked crop (zeros for an empty mask)."""
        rgb = np.asarray(rgb, np.float32)
        mask = np.asarray(mask, bool)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
        if mask.shape != rgb.shape[:2]:
            raise ValueError(f"mask shape {mask.shape} does not match rgb {rgb.shape[:2]}")
        rows, cols = np.nonzero(mask)
        if len(rows) == 0:
            return np.zeros_like(np.asarray(self.encoder.embed(np.full((self.min_size,) * 2 + (3,), 0.5, np.float32))))
        H, W = mask.shape
        pr = max(0, (self.min_size - (np.ptp(rows) + 1) + 1) // 2)
        pc = max(0, (self.min_size - (np.ptp(cols) + 1) + 1) // 2)
        r0, r1 = max(0, rows.min() - pr), min(H, rows.max() + 1 + pr)
        c0, c1 = max(0, cols.min() - pc), min(W, cols.max() + 1 + pc)
        crop = np.where(mask[r0:r1, c0:c1, None], rgb[r0:r1, c0:c1], np.float32(0.5))
        return np.asarray(self.encoder.embed(crop), np.float32)

    def similarity(self, a: np.ndarray, b: np.ndarray) -> float:
        """(cosine + 1) / 2 in [0, 1]; 0 when either signature is all zeros."""
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        if a.shape != b.shape:
            raise ValueError(f"signature shapes differ: {a.shape} vs {b.shape}")
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if na == 0 or nb == 0:
            return 0.0
        return float(np.clip((a @ b / (na * nb) + 1.0) / 2.0, 0.0, 1.0))


def goal_object_mask(detections: Iterable, goal_class: str) -> np.ndarray | None:
    """The goal object's (H, W) bool mask in the goal image: the largest of the
    :class:`~splatsearch.search.detection.Detection` s labelled ``goal_class`` (a goal image is
    framed on its object), or None when there is none."""
    masks = [d.mask for d in detections if d.label == goal_class]
    if not masks:
        return None
    return max(masks, key=lambda m: int(m.sum()))
