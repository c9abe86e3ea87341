"""Completing novel-view renders (the thesis' VCICN slot, Section 4.2.4).

Renders of a sparse Gaussian map have holes where nothing was observed. An :class:`Inpainter`
fills the masked pixels of a set of views. The offline default is OpenCV's Telea / Navier-Stokes
inpainting, one view at a time; it removes the hard black hole borders (which otherwise produce
spurious corner features) but invents no texture.

Plugging in a multi-view diffusion model such as the thesis' VCICN: implement
``inpaint(images, masks)`` over the whole stack at once. VCICN takes the N_R renders and their
hole masks together (eq 14-16): each view is VAE-encoded to a latent, the masks are downsampled
to the latent size, and the denoiser sees [noisy latents, masked clean latents, masks] of all
views jointly, so the completed views agree with each other; the first view's mask is set to
zero (``masks[0] = False``), as in training. :class:`DiffusionInpainter` is the per-view
single-image variant built on any local ``diffusers`` inpainting pipeline.
"""

from __future__ import annotations

import os
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Inpainter(Protocol):
    """Fills holes: ``inpaint(images (N, H, W, 3) float in [0, 1], masks (N, H, W) bool, True =
    fill) -> (N, H, W, 3) float32``, with unmasked pixels unchanged."""

    def inpaint(self, images: np.ndarray, masks: np.ndarray) -> np.ndarray: ...


def holes_from_alpha(alpha: np.ndarray, tau: float = 0.5) -> np.ndarray:
    """Hole masks of renders: True where the accumulated opacity is below ``tau``.

    alpha: (N, H, W), (N, H, W, 1), (H, W) or (H, W, 1). Returns bool of the same shape without
    the trailing channel axis.
    """
    a = np.asarray(alpha)
    if a.ndim >= 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3):
        raise ValueError(f"alpha must have shape (N, H, W) or (H, W) (optionally with a channel of 1), got {np.shape(alpha)}")
    if not 0.0 <= tau <= 1.0:
        raise ValueError(f"tau must be in [0, 1], got {tau}")
    return a < tau


def split_holes(holes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split hole masks into (interior, exterior): exterior holes are the connected hole regions
    (8-connected) that touch the image border, i.e. background around an object; interior holes
    are gaps enclosed by rendered content. holes: (N, H, W) or (H, W) bool; returns two bool
    arrays of the same shape.

    Used for object-centric renders: inpainting the large background region would smear the
    object's colours outwards and blur its silhouette, so the background is filled with a
    constant instead and only the enclosed gaps are inpainted.
    """
    import cv2

    h = np.asarray(holes)
    if h.dtype != bool or h.ndim not in (2, 3):
        raise ValueError(f"holes must be a bool array of shape (N, H, W) or (H, W), got {h.dtype} {h.shape}")
    stack = h[None] if h.ndim == 2 else h
    ext = np.zeros_like(stack)
    for hv, ev in zip(stack, ext):
        if not hv.any():
            continue
        _n, lab = cv2.connectedComponents(hv.astype(np.uint8), connectivity=8)
        border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
        border = border[border > 0]
        ev[:] = np.isin(lab, border)
    ext = ext[0] if h.ndim == 2 else ext
    return h & ~ext, ext


def _check_stack(images, masks) -> tuple[np.ndarray, np.ndarray]:
    images = np.asarray(images, np.float32)
    masks = np.asarray(masks)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images must have shape (N, H, W, 3), got {images.shape}")
    if masks.dtype != bool or masks.shape != images.shape[:3]:
        raise ValueError(f"masks must be bool with shape {images.shape[:3]}, got {masks.dtype} {masks.shape}")
    if not np.all(np.isfinite(images)):
        raise ValueError("images contain NaN or Inf")
    return images, masks


class OpenCVInpainter:
    """OpenCV inpainting of every view independently.

    Args:
        method: "telea" (fast marching, Telea 2004) or "ns" (Navier-Stokes).
        radius: neighbourhood radius in pixels.
        max_side: views are inpainted at most this many pixels on their long side and the fill is
            upsampled back (inpainting cost grows with the hole area; the filled regions are
            smooth, so little is lost). None: full resolution.

    A view whose mask covers every pixel has nothing to propagate from and is returned unchanged.
    """

    def __init__(self, method: str = "telea", radius: float = 3.0, max_side: int | None = 160):
        if method not in ("telea", "ns"):
            raise ValueError(f"method must be 'telea' or 'ns', got {method!r}")
        if not radius > 0:
            raise ValueError(f"radius must be positive (pixels), got {radius}")
        if max_side is not None and max_side < 8:
            raise ValueError(f"max_side must be >= 8 or None, got {max_side}")
        self.method, self.radius, self.max_side = method, float(radius), max_side

    def inpaint(self, images: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) float32 with the masked pixels filled."""
        import cv2

        images, masks = _check_stack(images, masks)
        flag = cv2.INPAINT_TELEA if self.method == "telea" else cv2.INPAINT_NS
        out = images.copy()
        for img, m, dst in zip(images, masks, out):
            if not m.any() or m.all():
                continue
            u8 = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
            m8 = m.astype(np.uint8)
            H, W = m.shape
            s = 1.0 if self.max_side is None else min(1.0, self.max_side / max(H, W))
            if s < 1.0:
                size = (max(1, round(W * s)), max(1, round(H * s)))
                small = cv2.resize(u8, size, interpolation=cv2.INTER_AREA)
                # a small-image pixel is a hole if any of its source pixels is, so no black
                # hole colour leaks into the fill
                ms = cv2.resize(m8, size, interpolation=cv2.INTER_AREA) > 0
                if ms.all():
                    continue
                filled = cv2.inpaint(small, ms.astype(np.uint8), max(1.0, self.radius * s), flag)
                filled = cv2.resize(filled, (W, H), interpolation=cv2.INTER_LINEAR)
            else:
                filled = cv2.inpaint(u8, m8, self.radius, flag)
            dst[m] = filled[m].astype(np.float32) / 255.0
        return out


class DiffusionInpainter:
    """Single-image diffusion inpainting with a local ``diffusers`` pipeline, view by view.

    Loads ``diffusers.AutoPipelineForInpainting.from_pretrained(model_path,
    local_files_only=True)`` on first use (never downloads) and calls it once per view with the
    view and its hole mask (white = repaint). Views without holes are passed through; the
    known pixels of every output are copied back from the input so only holes change.

    Args:
        model_path: local directory of a diffusers inpainting pipeline (e.g. a Stable Diffusion
            inpainting checkpoint saved with ``save_pretrained``).
        prompt: text prompt; the thesis conditions on the goal class, e.g. "a photo of a chair".
        num_inference_steps, guidance_scale, strength: passed to the pipeline.
        device: torch device ("cuda", "cpu"); torch_dtype: e.g. "float16" on GPU.
        seed: generator seed, for reproducible fills.

    Raises:
        FileNotFoundError: if ``model_path`` does not exist.
        ImportError: on first use if ``diffusers`` / ``torch`` are missing.
    """

    def __init__(self, model_path: str | os.PathLike, prompt: str = "", num_inference_steps: int = 25,
                 guidance_scale: float = 7.5, strength: float = 1.0, device: str = "cpu",
                 torch_dtype: str | None = None, seed: int = 0):
        self.model_path = os.fspath(model_path)
        if not os.path.exists(self.model_path):
            raise FileNotFoundError(f"diffusion model not found: {self.model_path!r} (models are never downloaded)")
        if num_inference_steps < 1 or not 0.0 < strength <= 1.0:
            raise ValueError("need num_inference_steps >= 1 and 0 < strength <= 1")
        self.prompt, self.steps, self.guidance, self.strength = prompt, int(num_inference_steps), float(guidance_scale), float(strength)
        self.device, self.torch_dtype, self.seed = device, torch_dtype, int(seed)
        self._pipe = None

    def _load(self):
        if self._pipe is None:
            try:
                import torch
                from diffusers import AutoPipelineForInpainting
            except ImportError as e:
                raise ImportError("DiffusionInpainter needs 'diffusers' and 'torch' (pip install diffusers torch)") from e
            kw = {"local_files_only": True}
            if self.torch_dtype is not None:
                kw["torch_dtype"] = getattr(torch, self.torch_dtype)
            self._pipe = AutoPipelineForInpainting.from_pretrained(self.model_path, **kw).to(self.device)
            self._pipe.set_progress_bar_config(disable=True)
        return self._pipe

    def inpaint(self, images: np.ndarray, masks: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) float32 with the masked pixels repainted by the diffusion model."""
        images, masks = _check_stack(images, masks)
        pipe = self._load()  # first, so a missing package fails with the clear message
        import torch
        from PIL import Image

        out = images.copy()
        N, H, W = masks.shape
        # latent diffusion works on multiples of 8 pixels
        h8, w8 = max(8, H // 8 * 8), max(8, W // 8 * 8)
        for i in range(N):
            if not masks[i].any():
                continue
            img = Image.fromarray((np.clip(images[i], 0, 1) * 255 + 0.5).astype(np.uint8)).resize((w8, h8))
            msk = Image.fromarray(masks[i].astype(np.uint8) * 255).resize((w8, h8), Image.NEAREST)
            gen = torch.Generator(device="cpu").manual_seed(self.seed + i)
            res = pipe(prompt=self.prompt, image=img, mask_image=msk, height=h8, width=w8,
                       num_inference_steps=self.steps, guidance_scale=self.guidance, strength=self.strength,
                       generator=gen).images[0]
            filled = np.asarray(res.convert("RGB").resize((W, H), Image.BILINEAR), np.float32) / 255.0
            out[i][masks[i]] = filled[masks[i]]
        return out
