"""Plug-in models from spec strings: ``make_detector("yolo:/models/yolov8n-seg.pt")``.

The search agent takes a detector, a matcher, an inpainter and an image encoder as objects.
Front ends (the CLI, :func:`splatsearch.evaluation.evaluate`, whose episodes run in worker
processes) pass a short, picklable *spec string* instead and build the object where it is used.

Spec grammar::

    KIND[:PATH][,KEY=VALUE]...

``PATH`` is a local file or directory (weights are never downloaded; it may not contain a
comma). ``VALUE`` is read as an int, a float, ``true`` / ``false`` / ``none``, or else kept as
a string. Building a plug-in loads nothing heavy: model libraries are imported and weights read
on first use, so calling ``make_*`` once in the parent process checks a spec (unknown kind,
unknown option, missing file) before any worker starts.

Kinds (see :data:`SPEC_HELP`, and docs/models.md for what each file must hold):

=========== =================================== =============================================
factory     kind                                class
=========== =================================== =============================================
detector    ``sim``                             :class:`~splatsearch.search.SimDetector`
detector    ``yolo:PATH[,sam=PATH]``            :class:`~splatsearch.search.UltralyticsDetector`
matcher     ``sift``                            :class:`~splatsearch.search.SIFTMatcher`
matcher     ``rootsift``, ``features``, ...     :class:`~splatsearch.search.matching.LocalFeatureMatcher`
matcher     ``loftr:PATH``                      :class:`~splatsearch.search.LoFTRMatcher`
inpainter   ``auto``                            ``vcicn`` when the package ships its weights, else ``opencv``
inpainter   ``vcicn[:PATH]``                    :class:`~splatsearch.search.completion.VCICNInpainter`
inpainter   ``opencv``                          :class:`~splatsearch.search.OpenCVInpainter`
inpainter   ``diffusion:PATH``                  :class:`~splatsearch.search.DiffusionInpainter`
encoder     ``colortexture``                    :class:`~splatsearch.nav.encoders.ColorTextureEncoder`
encoder     ``openclip:PATH[,model_name=NAME]`` :class:`~splatsearch.nav.encoders.OpenCLIPEncoder`
encoder     ``transformers:PATH``               :class:`~splatsearch.nav.encoders.TransformersImageEncoder`
=========== =================================== =============================================
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "SPEC_HELP",
    "DETECTOR_HELP",
    "MATCHER_HELP",
    "INPAINTER_HELP",
    "ENCODER_HELP",
    "PluginSpec",
    "parse_spec",
    "make_detector",
    "make_matcher",
    "make_inpainter",
    "resolve_inpainter_spec",
    "make_encoder",
]

DETECTOR_HELP = ("goal-class detector: 'sim' (the simulator's ground-truth masks, an oracle; default) or "
                 "'yolo:PATH[,sam=PATH][,conf=0.35][,min_pixels=150][,imgsz=640][,max_det=300][,device=cpu]' (an ultralytics "
                 "YOLO .pt/.onnx file; a box-only model with sam=PATH gets SAM/MobileSAM masks)")
MATCHER_HELP = ("goal-image matcher: 'sift[,contrast_threshold=0.04][,ratio=0.75]' (OpenCV SIFT + RANSAC; "
                "default), 'rootsift' / 'akaze' (RootSIFT or AKAZE, ratio test + mutual nearest neighbours + "
                "RANSAC), 'sift-essential' (SIFT + ratio test + essential-matrix RANSAC with the known "
                "intrinsics), 'features[,detector=sift|rootsift|akaze][,mutual=true][,gms=false][,colour_tol=none]"
                "[,model=fundamental|homography|essential|none][,min_inlier_ratio=0]' (every option; "
                "docs/matching.md) or 'loftr:PATH[,conf_thresh=0.5][,max_side=640][,device=cpu]' (a kornia LoFTR "
                "checkpoint)")
INPAINTER_HELP = ("novel-view completion: 'auto' (default: the VCICN with the weights shipped in the package, "
                  "or OpenCV when none are shipped), 'vcicn[:FILE.npz][,composite=holes|over]' (the multi-view "
                  "completion network; FILE from `splatsearch vcicn train`; docs/vcicn.md), 'opencv[,method=telea]' or 'diffusion:DIR[,prompt=TEXT]"
                  "[,num_inference_steps=25][,device=cpu]' (a local diffusers inpainting pipeline directory)")
ENCODER_HELP = ("image encoder for the value map: 'colortexture' (default), 'openclip:FILE[,model_name=ViT-B-32]' "
                "or 'transformers:DIR' (a CLIP / SigLIP / BLIP-2 save_pretrained directory)")
SPEC_HELP = ("plug-in spec KIND[:PATH][,KEY=VALUE...]; weights are read from local paths only, never downloaded. "
             f"{DETECTOR_HELP}; {MATCHER_HELP}; {INPAINTER_HELP}; {ENCODER_HELP}")


@dataclass(frozen=True)
class PluginSpec:
    """A parsed spec: ``kind``, ``path`` (None when the spec has none) and ``options`` (typed)."""

    kind: str
    path: str | None = None
    options: dict[str, Any] = field(default_factory=dict)


def _value(text: str) -> Any:
    low = text.lower()
    if low in ("true", "yes"):
        return True
    if low in ("false", "no"):
        return False
    if low in ("none", "null"):
        return None
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def parse_spec(spec: str) -> PluginSpec:
    """Split ``KIND[:PATH][,KEY=VALUE]...`` into a :class:`PluginSpec` (syntax only: no check of
    the kind, the options or the path). Raises ValueError for an empty spec, an empty kind or
    path, an option without ``=`` or a repeated option."""
    if not isinstance(spec, str):
        raise TypeError(f"a plug-in spec is a string such as 'sift' or 'loftr:/path/to.ckpt', got {type(spec).__name__}")
    head, *opts = [p.strip() for p in spec.strip().split(",")]
    if not head:
        raise ValueError(f"empty plug-in spec {spec!r}; expected KIND[:PATH][,KEY=VALUE...]")
    kind, sep, path = head.partition(":")
    kind = kind.strip().lower()
    if not kind:
        raise ValueError(f"plug-in spec {spec!r} has no kind before ':'")
    if sep and not path.strip():
        raise ValueError(f"plug-in spec {spec!r} has an empty path after '{kind}:'")
    options: dict[str, Any] = {}
    for opt in opts:
        key, eq, val = opt.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ValueError(f"option {opt!r} in plug-in spec {spec!r} is not KEY=VALUE "
                             "(paths may not contain commas)")
        if key in options:
            raise ValueError(f"option {key!r} given twice in plug-in spec {spec!r}")
        options[key] = _value(val.strip())
    return PluginSpec(kind, os.path.expanduser(path.strip()) if sep else None, options)


@dataclass(frozen=True)
class _Kind:
    build: Callable[..., Any]
    needs_path: bool | None  # None: the path is optional
    options: tuple[str, ...]
    path_is_dir: bool | None = False  # None: a file or a directory


def _build(what: str, kinds: dict[str, _Kind], spec: str, help_text: str, **extra) -> Any:
    ps = parse_spec(spec)
    k = kinds.get(ps.kind)
    if k is None:
        raise ValueError(f"unknown {what} kind {ps.kind!r} in {spec!r}; known: {', '.join(sorted(kinds))}. "
                         f"Usage: {help_text}")
    if k.needs_path is True and ps.path is None:
        raise ValueError(f"{what} kind {ps.kind!r} needs a local path: '{ps.kind}:PATH' (got {spec!r})")
    if k.needs_path is False and ps.path is not None:
        raise ValueError(f"{what} kind {ps.kind!r} takes no path (got {spec!r})")
    bad = sorted(set(ps.options) - set(k.options))
    if bad:
        allowed = ", ".join(k.options) or "none"
        raise ValueError(f"unknown option(s) {bad} for {what} kind {ps.kind!r}; allowed: {allowed}")
    if ps.path is not None:
        if k.path_is_dir is True and not os.path.isdir(ps.path):
            raise FileNotFoundError(f"{what} {ps.kind!r}: directory not found: {ps.path!r} (models are read from "
                                    "local paths only, never downloaded)")
        if k.path_is_dir is False and not os.path.isfile(ps.path):
            raise FileNotFoundError(f"{what} {ps.kind!r}: file not found: {ps.path!r} (weights are read from local "
                                    "paths only, never downloaded)")
        if k.path_is_dir is None and not os.path.exists(ps.path):
            raise FileNotFoundError(f"{what} {ps.kind!r}: path not found: {ps.path!r} (models are read from local "
                                    "paths only, never downloaded)")
        return k.build(ps.path, **ps.options, **extra)
    return k.build(**ps.options, **extra)


# -- detectors --------------------------------------------------------------------------------

def _sim_detector(goal_classes=None, **opts):
    from splatsearch.search.detection import SimDetector
    from splatsearch.sim.house import GOAL_CLASSES

    return SimDetector(goal_classes=tuple(goal_classes) if goal_classes else GOAL_CLASSES, **opts)


def _yolo_detector(path, goal_classes=None, sam=None, **opts):
    from splatsearch.search.detection import COCO_TO_GOAL, UltralyticsDetector

    class_map = None
    if goal_classes:
        keep = set(goal_classes)
        class_map = {name: (lab if lab in keep else None) for name, lab in COCO_TO_GOAL.items()}
    return UltralyticsDetector(path, class_map=class_map, sam_weights_path=sam, **opts)


_DETECTORS = {
    "sim": _Kind(_sim_detector, False, ("min_pixels",)),
    "yolo": _Kind(_yolo_detector, True, ("sam", "conf", "min_pixels", "device", "imgsz", "max_det")),
}


def make_detector(spec: str, goal_classes: tuple[str, ...] | list[str] | None = None):
    """A :class:`~splatsearch.search.Detector` from ``spec`` ('sim' or 'yolo:PATH[,sam=PATH]...').

    goal_classes: report only these labels (the agent needs only its goal class; the simulator
    detector then splits no other class). Raises ValueError (unknown kind or option, missing
    path) or FileNotFoundError (a path that does not exist)."""
    return _build("detector", _DETECTORS, spec, DETECTOR_HELP, goal_classes=goal_classes)


# -- matchers ---------------------------------------------------------------------------------

def _sift_matcher(renders=False, **opts):
    from splatsearch.search.matching import SIFTMatcher

    if renders and "contrast_threshold" not in opts:
        return SIFTMatcher.for_renders(**opts)
    return SIFTMatcher(**opts)


def _loftr_matcher(path, renders=False, **opts):
    from splatsearch.search.matching import LoFTRMatcher

    return LoFTRMatcher(path, **opts)


def _preset_matcher(preset):
    def build(renders=False, **opts):
        from splatsearch.search.matching import MATCHER_PRESETS, RENDER_CONTRAST_THRESHOLD, LocalFeatureMatcher

        kw = dict(MATCHER_PRESETS.get(preset, {}))
        # camera images keep OpenCV's SIFT contrast threshold, renders the lower one (see SIFTMatcher)
        kw.setdefault("contrast_threshold", RENDER_CONTRAST_THRESHOLD if renders else 0.04)
        kw.update(opts)
        return LocalFeatureMatcher(**kw)

    return build


_SIFT_OPTS = ("ratio", "ransac_thresh", "min_matches", "model", "n_features", "contrast_threshold")
_LOCAL_OPTS = ("detector", "ratio", "mutual", "gms", "colour_tol", "model", "ransac_thresh", "min_matches",
               "min_inlier_ratio", "contrast_threshold", "akaze_threshold", "n_features", "hfov_deg", "colour_radius",
               "gms_grid", "gms_alpha")
_MATCHERS = {
    "sift": _Kind(_sift_matcher, False, _SIFT_OPTS),
    # LocalFeatureMatcher: 'features' takes every option, the others are its named presets
    "features": _Kind(_preset_matcher("features"), False, _LOCAL_OPTS),
    "rootsift": _Kind(_preset_matcher("rootsift"), False, _LOCAL_OPTS),
    "akaze": _Kind(_preset_matcher("akaze"), False, _LOCAL_OPTS),
    "sift-essential": _Kind(_preset_matcher("sift-essential"), False, _LOCAL_OPTS),
    "loftr": _Kind(_loftr_matcher, True, ("conf_thresh", "max_side", "ransac_thresh", "model", "min_matches",
                                          "device")),
}


def make_matcher(spec: str, renders: bool = False):
    """A :class:`~splatsearch.search.Matcher` from ``spec`` ('sift' or 'loftr:PATH'...).

    renders: build the matcher for rendered novel views (the agent's ``nvsm_matcher``): for
    'sift' without an explicit ``contrast_threshold`` that is
    :meth:`~splatsearch.search.SIFTMatcher.for_renders`; other kinds ignore it. So
    ``make_matcher("sift")`` and ``make_matcher("sift", renders=True)`` are the agent's two
    defaults."""
    return _build("matcher", _MATCHERS, spec, MATCHER_HELP, renders=renders)


# -- inpainters -------------------------------------------------------------------------------

def _opencv_inpainter(**opts):
    from splatsearch.search.inpainting import OpenCVInpainter

    return OpenCVInpainter(**opts)


def _diffusion_inpainter(path, **opts):
    from splatsearch.search.inpainting import DiffusionInpainter

    return DiffusionInpainter(path, **opts)


def _vcicn_inpainter(path=None, **opts):
    from splatsearch.search.completion import VCICNInpainter

    return VCICNInpainter(path, **opts)


def _auto_inpainter(**opts):
    return _build("inpainter", _INPAINTERS, resolve_inpainter_spec("auto"), INPAINTER_HELP)


_INPAINTERS = {
    "auto": _Kind(_auto_inpainter, False, ()),
    "vcicn": _Kind(_vcicn_inpainter, None, ("sha256", "composite")),
    "opencv": _Kind(_opencv_inpainter, False, ("method", "radius", "max_side")),
    "diffusion": _Kind(_diffusion_inpainter, True, ("prompt", "num_inference_steps", "guidance_scale", "strength",
                                                    "device", "torch_dtype", "seed"), path_is_dir=True),
}


def resolve_inpainter_spec(spec: str) -> str:
    """``spec`` with ``auto`` replaced: ``vcicn`` when the package ships VCICN weights, else
    ``opencv`` (checks that the file is present; loads nothing)."""
    if parse_spec(spec).kind != "auto":
        return spec
    from splatsearch.search.completion import shipped_weights_available

    return "vcicn" if shipped_weights_available() else "opencv"


def make_inpainter(spec: str):
    """An :class:`~splatsearch.search.Inpainter` from ``spec`` ('auto', 'vcicn[:FILE]', 'opencv' or
    'diffusion:DIR'...). 'vcicn' without a path reads the shipped weights and checks their
    checksum here (a corrupt file fails before any worker starts)."""
    return _build("inpainter", _INPAINTERS, spec, INPAINTER_HELP)


# -- image encoders ---------------------------------------------------------------------------

def _colortexture_encoder(**opts):
    from splatsearch.nav.encoders import ColorTextureEncoder

    return ColorTextureEncoder(**opts)


def _openclip_encoder(path, **opts):
    from splatsearch.nav.encoders import OpenCLIPEncoder

    return OpenCLIPEncoder(path, **opts)


def _transformers_encoder(path, **opts):
    from splatsearch.nav.encoders import TransformersImageEncoder

    return TransformersImageEncoder(path, **opts)


_ENCODERS = {
    "colortexture": _Kind(_colortexture_encoder, False, ("size",)),
    "openclip": _Kind(_openclip_encoder, True, ("model_name", "device")),
    "transformers": _Kind(_transformers_encoder, True, ("device",), path_is_dir=True),
}


def make_encoder(spec: str):
    """An :class:`~splatsearch.nav.encoders.ImageEncoder` from ``spec`` ('colortexture',
    'openclip:FILE[,model_name=NAME]' or 'transformers:DIR'). Raises
    :class:`~splatsearch.nav.encoders.ModelUnavailable` when the model library is missing."""
    return _build("encoder", _ENCODERS, spec, ENCODER_HELP)
