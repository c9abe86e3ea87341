"""Goal-class detection: the SOIM's 2-D front end (thesis Section 4.2.2).

A detector turns one RGB image into instance masks of goal-class objects, each with a class label
and a confidence. It never says *which* instance a mask belongs to: telling the goal instance
apart from others of its class is the whole point of the search (NVSM + FEM), so identities must
not leak through the detector.

Two implementations:

* :class:`SimDetector`, the offline default: reads the simulator frame's class and instance maps
  (an oracle segmenter with perfect masks) and keeps only labels and masks.
* :class:`UltralyticsDetector`: a YOLO-seg style model from a local weights file (optionally with
  a SAM / MobileSAM model turning boxes into masks, as in the thesis' YOLOv7 + MobileSAM).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from splatsearch.sim.house import CLASS_IDS, GOAL_CLASSES

#: COCO names (as used by YOLO models trained on COCO) mapped to the thesis' goal classes.
COCO_TO_GOAL = {"chair": "chair", "couch": "sofa", "sofa": "sofa", "dining table": "table", "table": "table",
                "tv": "tv_monitor", "tvmonitor": "tv_monitor", "monitor": "tv_monitor", "laptop": None,
                "potted plant": "plant", "pottedplant": "plant", "bed": "bed"}


@dataclass(frozen=True, eq=False)
class Detection:
    """One detected object: mask (H, W) bool, class label (e.g. "chair"), score in [0, 1].

    Deliberately has no instance identity (see the module docstring).
    """

    mask: np.ndarray
    label: str
    score: float

    def __post_init__(self):
        mask = np.asarray(self.mask)
        if mask.ndim != 2 or mask.dtype != bool:
            raise ValueError(f"mask must be a 2-D bool array, got {mask.dtype} {mask.shape}")
        if not isinstance(self.label, str) or not self.label:
            raise ValueError(f"label must be a non-empty string, got {self.label!r}")
        if not (np.isfinite(self.score) and 0.0 <= self.score <= 1.0):
            raise ValueError(f"score must be in [0, 1], got {self.score}")
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "score", float(self.score))

    @property
    def n_pixels(self) -> int:
        return int(self.mask.sum())


@runtime_checkable
class Detector(Protocol):
    """Finds goal-class objects in an image.

    ``detect(rgb, frame=None)``: rgb (H, W, 3) float32 in [0, 1]; ``frame`` is an optional
    simulator :class:`~splatsearch.sim.Frame` (only oracle detectors need it). Returns a list of
    :class:`Detection` with (H, W) masks.
    """

    def detect(self, rgb: np.ndarray, frame: Any = None) -> list[Detection]: ...


def check_detections(dets: Any, shape: tuple[int, int], source: str = "detector") -> list[Detection]:
    """Validate what a :class:`Detector` returned for an (H, W) image: a list (or other iterable)
    of :class:`Detection` whose masks are (H, W). Plug-in models often return masks at their own
    input resolution; that would otherwise surface later as an indexing error far from its cause.

    Returns the detections as a list. Raises TypeError (anything but an iterable of Detection) or
    ValueError (a mask of another size), naming ``source``.
    """
    if not isinstance(dets, Iterable) or isinstance(dets, (str, bytes, dict, np.ndarray)):
        raise TypeError(f"{source}.detect must return a list of Detection, got {type(dets).__name__}")
    out = list(dets)
    shape = tuple(int(s) for s in shape)
    for i, d in enumerate(out):
        if not isinstance(d, Detection):
            raise TypeError(f"{source}.detect returned {type(d).__name__} at index {i}; expected a Detection "
                             "(mask (H, W) bool, label, score)")
        if d.mask.shape != shape:
            raise ValueError(f"{source}.detect returned a mask of shape {d.mask.shape} at index {i} for an image "
                             f"of {shape}; masks must have the image's size (resize them to (H, W) first)")
    return out


def _check_rgb(rgb) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError(f"rgb must have shape (H, W, 3), got {rgb.shape}")
    return rgb


class SimDetector:
    """Oracle detector over the simulator's class and instance maps.

    Every visible goal-class instance with at least ``min_pixels`` pixels becomes one detection
    with score 1. The instance map is used only to split a class into separate masks; the
    detections are sorted by area (then by first pixel), not by instance id, so not even their
    order reveals identities.

    Args:
        goal_classes: class names to report (default: the six goal classes).
        min_pixels: smallest mask kept, in pixels (tiny slivers cannot be lifted reliably).
    """

    def __init__(self, goal_classes: tuple[str, ...] | list[str] = GOAL_CLASSES, min_pixels: int = 150):
        unknown = [c for c in goal_classes if c not in CLASS_IDS]
        if unknown:
            raise ValueError(f"unknown class(es) {unknown}; known: {sorted(CLASS_IDS)}")
        if int(min_pixels) < 1:
            raise ValueError(f"min_pixels must be >= 1, got {min_pixels}")
        self.goal_classes = tuple(goal_classes)
        self.min_pixels = int(min_pixels)
        self._ids = {CLASS_IDS[c]: c for c in self.goal_classes}

    def detect(self, rgb: np.ndarray, frame: Any = None) -> list[Detection]:
        """Detections of goal-class instances in ``frame`` (a simulator Frame with ``class_id`` and
        ``instance`` (H, W) maps matching ``rgb``)."""
        rgb = _check_rgb(rgb)
        if frame is None or not hasattr(frame, "class_id") or not hasattr(frame, "instance"):
            raise ValueError("SimDetector needs the simulator frame (with class_id and instance maps)")
        cls, inst = np.asarray(frame.class_id), np.asarray(frame.instance)
        if cls.shape != rgb.shape[:2] or inst.shape != rgb.shape[:2]:
            raise ValueError(f"frame maps {cls.shape}/{inst.shape} do not match rgb {rgb.shape[:2]}")
        out = []
        goal = np.isin(cls, list(self._ids))
        for iid in np.unique(inst[goal]):
            mask = goal & (inst == iid)
            n = int(mask.sum())
            if n < self.min_pixels:
                continue
            label = self._ids[int(np.bincount(cls[mask]).argmax())]
            out.append((n, int(np.argmax(mask.ravel())), Detection(mask, label, 1.0)))
        out.sort(key=lambda t: (-t[0], t[1]))
        return [d for _, _, d in out]


def _resize_mask(m: np.ndarray, H: int, W: int) -> np.ndarray:
    import cv2

    return cv2.resize(m.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)


class UltralyticsDetector:
    """YOLO-seg style detector loaded from a local weights file (never downloads).

    With a segmentation model (``yolo*-seg``) the masks come from the model. With a box-only
    model, give ``sam_weights_path`` (a SAM / MobileSAM checkpoint that ``ultralytics.SAM``
    reads) to turn the boxes into masks, as the thesis does with YOLOv7 + MobileSAM; without it a
    box-only model's detections are filled boxes.

    Args:
        weights_path: local ``.pt`` / ``.onnx`` file for ``ultralytics.YOLO``.
        class_map: model class name -> goal label (None drops the class); default
            :data:`COCO_TO_GOAL`. Names not in the map are dropped.
        conf: minimum confidence.
        min_pixels: smallest mask kept.
        device: torch device string ("cpu", "cuda:0"); None lets ultralytics pick.
        sam_weights_path: optional local SAM checkpoint for box-only models (ultralytics picks
            the architecture from the file name: ``mobile_sam.pt``, ``sam_b.pt``, ...).
        imgsz: inference size in pixels (None: the model's default, 640 for YOLO).
        max_det: most detections kept per image (after NMS).

    Raises:
        FileNotFoundError: if a weights path does not exist (checked before anything is imported,
            so the library never falls back to downloading a model by name).
        ImportError: on first use if ``ultralytics`` is not installed.
    """

    def __init__(self, weights_path: str | os.PathLike, class_map: dict[str, str | None] | None = None,
                 conf: float = 0.35, min_pixels: int = 150, device: str | None = None,
                 sam_weights_path: str | os.PathLike | None = None, imgsz: int | None = None,
                 max_det: int = 300):
        self.weights_path = os.fspath(weights_path)
        if not os.path.isfile(self.weights_path):
            raise FileNotFoundError(f"detector weights not found: {self.weights_path!r} (weights are never downloaded)")
        self.sam_weights_path = None if sam_weights_path is None else os.fspath(sam_weights_path)
        if self.sam_weights_path is not None and not os.path.isfile(self.sam_weights_path):
            raise FileNotFoundError(f"SAM weights not found: {self.sam_weights_path!r}")
        if not 0.0 <= conf <= 1.0:
            raise ValueError(f"conf must be in [0, 1], got {conf}")
        self.class_map = dict(COCO_TO_GOAL if class_map is None else class_map)
        if imgsz is not None and int(imgsz) < 32:
            raise ValueError(f"imgsz must be >= 32 pixels or None, got {imgsz}")
        if int(max_det) < 1:
            raise ValueError(f"max_det must be >= 1, got {max_det}")
        self.conf, self.min_pixels, self.device = float(conf), int(min_pixels), device
        self.imgsz, self.max_det = None if imgsz is None else int(imgsz), int(max_det)
        self._model = None
        self._sam = None

    def _load(self):
        if self._model is None:
            try:
                from ultralytics import SAM, YOLO
            except ImportError as e:
                raise ImportError("UltralyticsDetector needs the 'ultralytics' package (pip install ultralytics)") from e
            self._model = YOLO(self.weights_path)
            if self.sam_weights_path is not None:
                self._sam = SAM(self.sam_weights_path)
        return self._model

    def detect(self, rgb: np.ndarray, frame: Any = None) -> list[Detection]:
        """Detections in ``rgb`` (H, W, 3) float in [0, 1]; ``frame`` is ignored."""
        rgb = _check_rgb(rgb)
        model = self._load()
        H, W = rgb.shape[:2]
        # ultralytics treats numpy input as OpenCV-style BGR uint8
        bgr = np.ascontiguousarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
        kw = {"conf": self.conf, "verbose": False, "retina_masks": True, "max_det": self.max_det}
        if self.device is not None:
            kw["device"] = self.device
        if self.imgsz is not None:
            kw["imgsz"] = self.imgsz
        res = model.predict(bgr, **kw)[0]
        if res.boxes is None or len(res.boxes) == 0:
            return []
        boxes = res.boxes.xyxy.cpu().numpy()
        cls = res.boxes.cls.cpu().numpy().astype(int)
        scores = res.boxes.conf.cpu().numpy()
        names = res.names
        if res.masks is not None:
            masks = res.masks.data.cpu().numpy() > 0.5
        else:
            masks = np.zeros((len(boxes), H, W), bool)
            for m, (x0, y0, x1, y1) in zip(masks, boxes):
                m[int(max(0, y0)):int(np.ceil(min(H, y1))), int(max(0, x0)):int(np.ceil(min(W, x1)))] = True
            if self._sam is not None:
                # SAM drops masks whose predicted IoU is below its own conf (0.25 by default), so its
                # output is not one mask per box; keep them all and place each by its prompt index
                # (the "cls" of SAM's results); a box SAM returns nothing for stays a filled box
                skw = {"conf": 0.0, "verbose": False, **({"device": self.device} if self.device else {})}
                sres = self._sam.predict(bgr, bboxes=boxes.tolist(), **skw)[0]
                if sres.masks is not None and sres.boxes is not None:
                    idx = sres.boxes.cls.cpu().numpy().astype(int)
                    for i, m in zip(idx, sres.masks.data.cpu().numpy() > 0.5):
                        masks[i] = m if m.shape == (H, W) else _resize_mask(m, H, W)
        out = []
        for m, c, s in zip(masks, cls, scores):
            label = self.class_map.get(str(names[int(c)]).lower())
            if label is None:
                continue
            if m.shape != (H, W):
                m = _resize_mask(m, H, W)
            if m.sum() >= self.min_pixels:
                out.append(Detection(m, label, float(np.clip(s, 0, 1))))
        return out
