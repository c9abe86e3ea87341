"""Image encoders for the value map (eq 11): ``embed(rgb) -> (D,)`` unit float32 vector.

* :class:`ColorTextureEncoder`: the offline default. A global descriptor built with OpenCV: a
  hue/saturation/value colour histogram, a gradient-orientation histogram and a rotation-invariant
  LBP histogram, on a 1x1 + 2x2 spatial pyramid. Each histogram is square-rooted (Hellinger) and
  centred on its own mean, so two descriptors' cosine is a correlation of histogram shapes (it
  can be negative) instead of the near-1 cosine of all-positive histograms.
* :class:`OpenCLIPEncoder` and :class:`TransformersImageEncoder`: adapters for CLIP / BLIP-2 style
  image towers whose weights are read from a local path. The heavy libraries are imported only
  when the model is loaded, and nothing is ever downloaded.
"""

from __future__ import annotations

import importlib.util
import os
from typing import Protocol, runtime_checkable

import cv2
import numpy as np


@runtime_checkable
class ImageEncoder(Protocol):
    """Anything that maps an RGB image (H, W, 3) float in [0, 1] (or uint8) to a (D,) unit
    float32 embedding."""

    def embed(self, rgb: np.ndarray) -> np.ndarray: ...


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    """Cosine similarity of two vectors (eq 11); 0 if either is all zeros."""
    a = np.asarray(a, np.float64).ravel()
    b = np.asarray(b, np.float64).ravel()
    if a.shape != b.shape:
        raise ValueError(f"embeddings differ in size: {a.shape} vs {b.shape}")
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return 0.0
    return float(a @ b / (na * nb))


def _as_rgb_float(rgb) -> np.ndarray:
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.shape[0] < 2 or a.shape[1] < 2:
        raise ValueError(f"rgb must be (H, W, 3) with H, W >= 2, got shape {a.shape}")
    a = a[..., :3]
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0
    a = a.astype(np.float32)
    if not np.all(np.isfinite(a)):
        raise ValueError("rgb contains non-finite values")
    return np.clip(a, 0.0, 1.0)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return (v / n).astype(np.float32) if n > 0 else v.astype(np.float32)


# rotation-invariant uniform LBP (P = 8): codes -> 10 bins (0..8 ones for uniform, 9 otherwise)
def _riu2_table() -> np.ndarray:
    t = np.zeros(256, np.int64)
    for code in range(256):
        bits = [(code >> i) & 1 for i in range(8)]
        transitions = sum(bits[i] != bits[(i + 1) % 8] for i in range(8))
        t[code] = sum(bits) if transitions <= 2 else 9
    return t


_RIU2 = _riu2_table()


class ColorTextureEncoder:
    """Colour-and-texture global descriptor (OpenCV); the offline :class:`ImageEncoder` default.

    Args:
        size: images are resized to ``size`` x ``size`` pixels first.
        hue_bins, sat_bins, val_bins: colour histogram bins for chromatic pixels; pixels with
            saturation below ``gray_sat`` go to ``gray_bins`` brightness bins instead (their hue
            is noise).
        orient_bins: unsigned gradient-orientation bins, weighted by gradient magnitude.
        color_weight, texture_weight: relative weight of the two halves before normalisation.
    """

    def __init__(self, size: int = 128, *, hue_bins: int = 12, sat_bins: int = 3, val_bins: int = 2,
                 gray_bins: int = 5, gray_sat: float = 0.15, orient_bins: int = 9,
                 color_weight: float = 1.0, texture_weight: float = 0.7):
        if size < 16:
            raise ValueError(f"size must be >= 16 pixels, got {size}")
        if min(hue_bins, sat_bins, val_bins, gray_bins, orient_bins) < 1:
            raise ValueError("every bin count must be >= 1")
        self.size = int(size)
        self.hue_bins, self.sat_bins, self.val_bins = int(hue_bins), int(sat_bins), int(val_bins)
        self.gray_bins, self.gray_sat = int(gray_bins), float(gray_sat)
        self.orient_bins = int(orient_bins)
        self.color_weight, self.texture_weight = float(color_weight), float(texture_weight)
        self.center: np.ndarray | None = None

    @property
    def dim(self) -> int:
        per_region = (self.hue_bins * self.sat_bins * self.val_bins + self.gray_bins) + self.orient_bins + 10
        return 5 * per_region

    def fit(self, images) -> ColorTextureEncoder:
        """Centre future embeddings on the mean descriptor of ``images`` (a sample of the
        environment): cosines then measure what sets an image apart from the typical view."""
        descs = [self._descriptor(im) for im in images]
        if not descs:
            raise ValueError("fit needs at least one image")
        self.center = np.mean(descs, 0)
        return self

    def embed(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) RGB in [0, 1] (or uint8) -> (D,) unit float32 descriptor."""
        d = self._descriptor(rgb)
        if self.center is not None:
            d = d - self.center
        return _unit(d)

    # -- internals ------------------------------------------------------------------------
    def _descriptor(self, rgb) -> np.ndarray:
        img = cv2.resize(_as_rgb_float(rgb), (self.size, self.size), interpolation=cv2.INTER_AREA)
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)  # H in [0, 360), S, V in [0, 1]
        h, s, v = hsv[..., 0], hsv[..., 1], hsv[..., 2]
        hb = np.minimum((h / 360.0 * self.hue_bins).astype(np.int64), self.hue_bins - 1)
        sb = np.minimum(((s - self.gray_sat) / (1 - self.gray_sat) * self.sat_bins).astype(np.int64), self.sat_bins - 1)
        vb = np.minimum((v * self.val_bins).astype(np.int64), self.val_bins - 1)
        gb = np.minimum((v * self.gray_bins).astype(np.int64), self.gray_bins - 1)
        n_chroma = self.hue_bins * self.sat_bins * self.val_bins
        color_code = np.where(s >= self.gray_sat, (hb * self.sat_bins + np.maximum(sb, 0)) * self.val_bins + vb,
                              n_chroma + gb)
        n_color = n_chroma + self.gray_bins

        gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        gray = cv2.GaussianBlur(gray, (3, 3), 0)
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
        mag = np.hypot(gx, gy)
        ang = np.mod(np.arctan2(gy, gx), np.pi)
        ob = np.minimum((ang / np.pi * self.orient_bins).astype(np.int64), self.orient_bins - 1)

        # LBP on the 8 neighbours; a small tolerance keeps flat regions from flickering with noise
        g = np.pad(gray, 1, mode="edge")
        Hh, Ww = gray.shape
        code = np.zeros(gray.shape, np.int64)
        shifts = [(-1, -1), (-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1)]
        for i, (dy, dx) in enumerate(shifts):
            nb = g[1 + dy:1 + dy + Hh, 1 + dx:1 + dx + Ww]
            code |= (nb >= gray + 0.02).astype(np.int64) << i
        lbp = _RIU2[code]

        parts = []
        S = self.size
        regions = [(slice(0, S), slice(0, S), 1.0)]
        half = S // 2
        for r in (slice(0, half), slice(half, S)):
            for c in (slice(0, half), slice(half, S)):
                regions.append((r, c, 0.5))
        for r, c, wgt in regions:
            hc = np.bincount(color_code[r, c].ravel(), minlength=n_color).astype(np.float64)
            ho = np.bincount(ob[r, c].ravel(), weights=mag[r, c].ravel(), minlength=self.orient_bins)
            hl = np.bincount(lbp[r, c].ravel(), minlength=10).astype(np.float64)
            parts.append(wgt * self.color_weight * _hellinger_centered(hc))
            parts.append(wgt * self.texture_weight * _hellinger_centered(ho))
            parts.append(wgt * self.texture_weight * _hellinger_centered(hl))
        return np.concatenate(parts)


def _hellinger_centered(hist: np.ndarray) -> np.ndarray:
    """sqrt of the normalised histogram, minus its mean bin, scaled to unit length (zeros for an
    empty or flat histogram)."""
    s = hist.sum()
    if s <= 0:
        return np.zeros_like(hist)
    h = np.sqrt(hist / s)
    h = h - h.mean()
    n = np.linalg.norm(h)
    return h / n if n > 1e-12 else np.zeros_like(h)


# ---------------------------------------------------------------------------------------------
# real-model adapters (weights from a local path, never downloaded)
# ---------------------------------------------------------------------------------------------

class ModelUnavailable(ImportError):
    """The library an adapter needs is not installed."""


def _require(module: str, pip_name: str, what: str) -> None:
    if importlib.util.find_spec(module) is None:
        raise ModelUnavailable(f"{what} needs the '{module}' package, which is not installed "
                               f"(pip install {pip_name}); the offline default is ColorTextureEncoder")


class OpenCLIPEncoder:
    """CLIP image tower from open_clip, with weights from a local checkpoint file.

    Args:
        checkpoint: path to the ``.pt`` / ``.bin`` / ``.safetensors`` weights of ``model_name``.
        model_name: open_clip architecture name, e.g. "ViT-B-32".
        device: torch device string.
    The model is loaded on the first :meth:`embed` (or :meth:`load`).
    """

    def __init__(self, checkpoint: str, model_name: str = "ViT-B-32", device: str = "cpu"):
        if not os.path.isfile(checkpoint):
            raise FileNotFoundError(f"open_clip checkpoint not found: {checkpoint!r} (weights are never downloaded)")
        _require("open_clip", "open_clip_torch", "OpenCLIPEncoder")
        _require("torch", "torch", "OpenCLIPEncoder")
        self.checkpoint, self.model_name, self.device = checkpoint, model_name, device
        self._model = self._preprocess = None

    def load(self) -> None:
        if self._model is not None:
            return
        import open_clip  # heavy: imported only here
        model, _, preprocess = open_clip.create_model_and_transforms(self.model_name, pretrained=self.checkpoint,
                                                                     device=self.device)
        model.eval()
        self._model, self._preprocess = model, preprocess

    def embed(self, rgb: np.ndarray) -> np.ndarray:
        import torch
        from PIL import Image

        self.load()
        img = Image.fromarray((_as_rgb_float(rgb) * 255).round().astype(np.uint8))
        x = self._preprocess(img).unsqueeze(0).to(self.device)
        with torch.no_grad():
            e = self._model.encode_image(x)
        return _unit(np.asarray(e.detach().cpu().numpy(), np.float64).reshape(-1))


class TransformersImageEncoder:
    """Image tower of a Hugging Face transformers model (CLIP, SigLIP, BLIP-2, ...) saved in a local
    directory (``save_pretrained`` layout). Loaded with ``local_files_only=True`` on first use.

    Args:
        model_dir: directory holding config.json, the weights and the image-processor config.
        device: torch device string.
    """

    def __init__(self, model_dir: str, device: str = "cpu"):
        if not os.path.isdir(model_dir):
            raise FileNotFoundError(f"model directory not found: {model_dir!r} (weights are never downloaded)")
        _require("transformers", "transformers", "TransformersImageEncoder")
        _require("torch", "torch", "TransformersImageEncoder")
        self.model_dir, self.device = model_dir, device
        self._model = self._processor = None

    def load(self) -> None:
        if self._model is not None:
            return
        import transformers  # heavy: imported only here

        self._processor = transformers.AutoImageProcessor.from_pretrained(self.model_dir, local_files_only=True)
        model = transformers.AutoModel.from_pretrained(self.model_dir, local_files_only=True)
        model.eval()
        self._model = model.to(self.device)

    def embed(self, rgb: np.ndarray) -> np.ndarray:
        import torch

        self.load()
        img = (_as_rgb_float(rgb) * 255).round().astype(np.uint8)
        inputs = self._processor(images=img, return_tensors="pt")
        pix = inputs["pixel_values"].to(self.device)
        with torch.no_grad():
            if hasattr(self._model, "get_image_features"):
                out = self._model.get_image_features(pixel_values=pix)
            else:
                out = self._model(pixel_values=pix)
        # CLIP returns a tensor; BLIP-2 and plain vision models return an output object
        for name in ("image_embeds", "pooler_output", "last_hidden_state"):
            if not hasattr(out, "shape") and getattr(out, name, None) is not None:
                out = getattr(out, name)
                if name == "last_hidden_state":
                    out = out.mean(1)
                break
        return _unit(np.asarray(out.detach().cpu().numpy(), np.float64).reshape(-1))
