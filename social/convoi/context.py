"""CoNVOI's context-based behaviour prompt (IV-A): contexts, behaviours, classifiers.

* :data:`CONTEXTS`: context -> behaviour phrase (the sets C and B of the paper). Add a scenario
  by adding a row; the prompt template takes the phrase as it is.
* :data:`PROMPT_TEMPLATE`: the behaviour prompt T_b of IV-A; :func:`behaviour_prompt` fills it.
* :class:`ContextClassifier` protocol: ``classify(image, scene) -> ContextResult`` (a probability
  per context, c_max) and ``is_paved(patch) -> bool`` (the IV-E paved-patch check).
* :class:`RuleContextClassifier`: the offline default, from occupancy geometry (corridor width,
  free length ahead, side openings, narrow gaps) and the detected people (count, groups,
  standing or walking). It ignores the image.
* :class:`CLIPContextClassifier`: zero-shot CLIP ("This is a picture of {c}") with weights from
  a local path, open_clip or transformers imported lazily; never downloads.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from .perception import LocalMap

CONTEXTS: dict[str, str] = {
    "an indoor corridor": "keeps close to the right wall",
    "a corridor with people walking towards the robot":
        "keeps to the right side of the corridor so that the oncoming people can pass on its left",
    "a blind corner in a corridor":
        "keeps to the right side and takes the corner wide, away from the inner corner where people may appear",
    "a doorway": "goes through the middle of the doorway and keeps away from people coming through it",
    "people standing in groups": "does not move in between people standing in a group and keeps a wide berth from them",
    "people walking in an open space":
        "keeps away from walking people, passes behind them rather than cutting in front of them, "
        "and does not move in between people walking together",
    "an open indoor space": "moves directly towards the goal",
    # outdoor contexts of the paper; the rule-based classifier never returns them
    "an outdoor sidewalk next to a road": "stays on the paved sidewalk",
    "a crosswalk": "crosses the road on the crosswalk",
    "outdoor terrain with grass and pavement": "moves on the pavement and avoids grass",
}
PROMPT_TEMPLATE = ("You are navigating a robot in this scenario. The numbers marked in the image denote regions "
                   "where you can navigate the robot. Pick a list of numbers marked in the image such that the "
                   "robot {behaviour}.")
CONTEXT_TEMPLATE = "This is a picture of {context}"
OPEN_SPACE = "an open indoor space"


def behaviour_prompt(context: str, table: dict[str, str] | None = None) -> str:
    """T_b for ``context``: the prompt template filled with its behaviour phrase."""
    table = CONTEXTS if table is None else table
    if context not in table:
        raise ValueError(f"unknown context {context!r}; known: {sorted(table)}")
    return PROMPT_TEMPLATE.format(behaviour=table[context])


@dataclass(frozen=True)
class SceneObservation:
    """What a context classifier may use besides the image (all in the robot frame: x forward,
    y left, metres). local_map: O_t with people; static_map: O_t without people; people: (k, 2);
    people_vel: (k, 2) m/s; groups: (k,) labels (-1 alone); goal: (2,) direction/point to the goal."""

    local_map: LocalMap
    static_map: LocalMap
    people: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    people_vel: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    groups: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    goal: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0]))


@dataclass(frozen=True)
class ContextResult:
    """label: c_max; probs: probability per context (sums to 1); features: what decided it."""

    label: str
    probs: dict[str, float]
    features: dict = field(default_factory=dict)


@runtime_checkable
class ContextClassifier(Protocol):
    def classify(self, image: np.ndarray | None, scene: SceneObservation | None = None) -> ContextResult: ...

    def is_paved(self, patch: np.ndarray) -> bool: ...


def _probs(label: str, labels, confidence: float = 0.85) -> dict[str, float]:
    labels = list(labels)
    rest = (1.0 - confidence) / max(len(labels) - 1, 1)
    return {c: (confidence if c == label else rest) for c in labels}


class RuleContextClassifier:
    """Offline context classifier from geometry and detected people (see the module doc).

    corridor_width: free width (m) below which the space ahead is a corridor; door_width: a gap
    narrower than this ahead of wider space is a doorway; people_range: people farther than
    this (m) do not change the context; static_speed: a group slower than this (m/s) stands.
    """

    needs_image = False

    def __init__(self, contexts: dict[str, str] | None = None, *, corridor_width: float = 3.2,
                 door_width: float = 1.6, people_range: float = 5.0, static_speed: float = 0.2,
                 corner_range: float = 4.5):
        self.contexts = CONTEXTS if contexts is None else contexts
        for c in ("an indoor corridor", "a corridor with people walking towards the robot",
                  "a blind corner in a corridor", "a doorway", "people standing in groups",
                  "people walking in an open space", OPEN_SPACE):
            if c not in self.contexts:
                raise ValueError(f"the rule-based classifier needs the context {c!r} in the table")
        self.corridor_width, self.door_width = float(corridor_width), float(door_width)
        self.people_range, self.static_speed = float(people_range), float(static_speed)
        self.corner_range = float(corner_range)

    @staticmethod
    def _extent(m: LocalMap, origin, direction, max_len: float, step: float = 0.05) -> float:
        s = np.arange(0.0, max_len + step, step)
        pts = np.asarray(origin)[None] + s[:, None] * np.asarray(direction)[None]
        blocked = m.clearance_at(pts) <= 0.05  # at a wall's surface (cells sample it at 5 cm)
        return float(s[np.argmax(blocked)]) if blocked.any() else float(max_len)

    def geometry(self, m: LocalMap) -> dict:
        """Free widths ahead, free length ahead and side openings, from the static map."""
        half = 0.5 * m.spec.shape[0] * m.spec.cell_size
        reach = min(half - 0.1, 4.5)
        ahead = self._extent(m, (0.0, 0.0), (1.0, 0.0), reach)
        xs = np.arange(0.25, max(min(ahead, reach), 0.3), 0.25)
        widths, lefts, rights = [], [], []
        for x in xs:
            lft = self._extent(m, (x, 0.0), (0.0, 1.0), reach)
            rgt = self._extent(m, (x, 0.0), (0.0, -1.0), reach)
            lefts.append(lft)
            rights.append(rgt)
            widths.append(lft + rgt)
        widths = np.asarray(widths) if widths else np.array([2 * reach])
        near = widths[: max(1, min(len(widths), 4))]  # within ~1 m of the robot
        return {"ahead": ahead, "width_near": float(np.median(near)), "width_min": float(widths.min()),
                "width_max": float(widths.max()), "side_open": float(max(max(lefts, default=0), max(rights, default=0))),
                "reach": reach}

    def classify(self, image: np.ndarray | None, scene: SceneObservation | None = None) -> ContextResult:
        """c_max from ``scene`` (required; the image is ignored)."""
        if scene is None:
            raise ValueError("RuleContextClassifier needs the scene observation (occupancy and people)")
        g = self.geometry(scene.static_map)
        ppl = np.asarray(scene.people, np.float64).reshape(-1, 2)
        vel = np.asarray(scene.people_vel, np.float64).reshape(-1, 2)
        grp = np.asarray(scene.groups).reshape(-1)
        near = np.linalg.norm(ppl, axis=1) < self.people_range if len(ppl) else np.zeros(0, bool)
        ahead_p = near & (ppl[:, 0] > -0.5) if len(ppl) else near
        standing_groups = 0
        for lab in set(grp[near].tolist()) - {-1}:
            m = near & (grp == lab)
            if m.sum() >= 2 and np.linalg.norm(vel[m], axis=1).mean() < self.static_speed:
                standing_groups += 1
        corridor = g["width_near"] < self.corridor_width
        doorway = (g["width_min"] < self.door_width and g["width_max"] > self.door_width + 1.0
                   and not corridor) or (g["width_near"] < self.door_width)
        # in a corridor, or at its junction, with a wall ahead and an opening to one side
        corner = ((corridor or g["width_min"] < self.corridor_width) and g["ahead"] < self.corner_range
                  and g["side_open"] > 3.0)
        if doorway:
            label = "a doorway"
        elif corner:
            label = "a blind corner in a corridor"
        elif corridor and ahead_p.any():
            label = "a corridor with people walking towards the robot"
        elif corridor:
            label = "an indoor corridor"
        elif standing_groups:
            label = "people standing in groups"
        elif near.any():
            label = "people walking in an open space"
        else:
            label = OPEN_SPACE
        feats = dict(g, people=int(near.sum()), standing_groups=standing_groups)
        return ContextResult(label, _probs(label, self.contexts), feats)

    def is_paved(self, patch: np.ndarray) -> bool:
        """Paved unless the patch is mostly vegetation-green (G clearly above R and B)."""
        p = np.asarray(patch, np.float32)
        if p.ndim != 3 or p.shape[2] < 3 or p.size == 0:
            raise ValueError(f"patch must be (h, w, 3), got shape {p.shape}")
        if p.dtype == np.uint8 or p.max() > 1.0:
            p = p / 255.0
        r, gch, b = p[..., 0], p[..., 1], p[..., 2]
        green = (gch > r + 0.08) & (gch > b + 0.08)
        return float(green.mean()) < 0.3


class ModelUnavailable(ImportError):
    """The package or the weights a model adapter needs are missing."""


class CLIPContextClassifier:
    """Zero-shot CLIP context classifier (CoNVOI IV-A) with weights from a local path.

    Args:
        model_path: an open_clip checkpoint file, or a transformers ``save_pretrained`` directory.
        backend: "open_clip" (file) or "transformers" (directory); default from the path type.
        model_name: the open_clip architecture, e.g. "ViT-B-32".
        contexts: the context table (its keys are the classes).
    The heavy packages are imported on first use; a missing package or file raises
    :class:`ModelUnavailable` / ``FileNotFoundError`` with the fix in the message.
    """

    needs_image = True

    def __init__(self, model_path: str, backend: str | None = None, model_name: str = "ViT-B-32",
                 contexts: dict[str, str] | None = None, device: str = "cpu"):
        if not os.path.exists(model_path):
            raise FileNotFoundError(f"CLIP weights not found at {model_path!r} (weights are never downloaded; "
                                    f"the offline default is RuleContextClassifier)")
        backend = backend or ("transformers" if os.path.isdir(model_path) else "open_clip")
        if backend not in ("open_clip", "transformers"):
            raise ValueError(f"backend must be 'open_clip' or 'transformers', got {backend!r}")
        needed = ["torch", "open_clip" if backend == "open_clip" else "transformers"]
        for mod in needed:
            if importlib.util.find_spec(mod) is None:
                pip = {"open_clip": "open_clip_torch"}.get(mod, mod)
                raise ModelUnavailable(f"CLIPContextClassifier ({backend}) needs the '{mod}' package "
                                       f"(pip install {pip}); the offline default is RuleContextClassifier")
        self.model_path, self.backend, self.model_name, self.device = model_path, backend, model_name, device
        self.contexts = CONTEXTS if contexts is None else contexts
        self._model = None

    def _load(self):
        if self._model is not None:
            return
        # weights come from model_path only (pretrained= a file, local_files_only=True): nothing is
        # downloaded, and the user's environment is left as it is
        if self.backend == "open_clip":
            import open_clip

            model, _, pre = open_clip.create_model_and_transforms(self.model_name, pretrained=self.model_path,
                                                                  device=self.device)
            self._model, self._pre, self._tok = model.eval(), pre, open_clip.get_tokenizer(self.model_name)
        else:
            import transformers

            self._proc = transformers.CLIPProcessor.from_pretrained(self.model_path, local_files_only=True)
            self._model = transformers.CLIPModel.from_pretrained(self.model_path, local_files_only=True).eval().to(self.device)

    def probabilities(self, image: np.ndarray, texts: list[str]) -> np.ndarray:
        """Softmax over ``texts`` of CLIP's image-text logits for ``image`` (H, W, 3)."""
        import torch
        from PIL import Image

        self._load()
        img = np.asarray(image)
        if img.dtype != np.uint8:
            img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
        pil = Image.fromarray(img[..., :3])
        with torch.no_grad():
            if self.backend == "open_clip":
                x = self._pre(pil).unsqueeze(0).to(self.device)
                fi = self._model.encode_image(x)
                ft = self._model.encode_text(self._tok(texts).to(self.device))
                fi = fi / fi.norm(dim=-1, keepdim=True)
                ft = ft / ft.norm(dim=-1, keepdim=True)
                logits = 100.0 * fi @ ft.T
            else:
                inp = self._proc(text=texts, images=pil, return_tensors="pt", padding=True).to(self.device)
                logits = self._model(**inp).logits_per_image
        return torch.softmax(logits, -1)[0].cpu().numpy().astype(np.float64)

    def classify(self, image: np.ndarray | None, scene: SceneObservation | None = None) -> ContextResult:
        if image is None:
            raise ValueError("CLIPContextClassifier needs the RGB image")
        labels = list(self.contexts)
        p = self.probabilities(image, [CONTEXT_TEMPLATE.format(context=c) for c in labels])
        k = int(np.argmax(p))
        return ContextResult(labels[k], {c: float(v) for c, v in zip(labels, p)})

    def is_paved(self, patch: np.ndarray) -> bool:
        p = self.probabilities(patch, ["This is a picture of a paved surface, an indoor floor or a sidewalk",
                                       "This is a picture of an unpaved surface: grass, gravel or an asphalt road"])
        return bool(p[0] >= p[1])
