"""Captions of OLiVia-Nav's views (thesis 3.3, D_SC and D_TSM): the action vocabulary, template
captions over the simulator's privileged scene (standing in for GPT-4o), a real VLM's captions
through the social module's HTTP client, and the action named by a caption.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from ..convoi.geometry import F32, DistanceField, world_to_robot
from .render import COLOURS, HFOV, MAX_RANGE, _cast, person_colour


LONG_LEN, SHORT_LEN = 96, 32    # token lengths of T_l and T_s
ACTIONS = ("straight", "keep_right", "keep_left", "turn_left", "turn_right", "yield")
ACTION_PHRASES = {
    "straight": ("continue moving straight ahead at a steady pace",
                 "keep going straight along the path"),
    "keep_right": ("keep to the right side and pass on the right",
                   "move gently to the right and keep right while passing"),
    "keep_left": ("move slightly to the left and pass on the left",
                  "keep to the left side of the path while passing"),
    "turn_left": ("turn left and follow the way around",
                  "gradually turn to the left"),
    "turn_right": ("turn right and follow the way around",
                   "gradually turn to the right"),
    "yield": ("slow down and yield to the people before moving on",
              "stop and give way to the people"),
}
_NUM = ("no", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten")
CAPTION_PROMPT = ("You are guiding a mobile robot among people. Describe this first-person image for the robot. "
                  "Reply with JSON {\"long\": ..., \"short\": ...}: 'long' describes the social scenario, the "
                  "people (clothing, where they are, how they move), the layout, and the high-level action the "
                  "robot should take to stay socially compliant (continue straight, keep right, keep left, turn "
                  "left, turn right, or slow down and yield); 'short' is one or two short sentences about the "
                  "people and the layout.")


@dataclass(frozen=True)
class Caption:
    """long: T_l; short: T_s; action: index into :data:`ACTIONS` read from T_l (-1: none);
    ok: usable; source: which captioner."""

    long: str
    short: str
    action: int
    ok: bool = True
    source: str = "template"


@dataclass(frozen=True)
class CaptionScene:
    """What a privileged captioner knows at one instant (robot frame, metres, m/s).

    context, description: the scenario's; seed; people: (k, 2) visible people; people_vel:
    (k, 2); colours: (k,) palette indices; groups: (k,) group ids (-1 alone); walls: (left,
    right, ahead) wall distances (m); action: the expert's action index."""

    context: str
    description: str
    seed: int
    people: np.ndarray
    people_vel: np.ndarray
    colours: np.ndarray
    groups: np.ndarray
    walls: tuple[float, float, float]
    action: int


@runtime_checkable
class Captioner(Protocol):
    """The large VLM of SC-CLIP and the LLU: caption an egocentric image."""

    def caption(self, image: np.ndarray, scene: CaptionScene | None = None) -> Caption: ...


def _bearing(p) -> str:
    a = np.degrees(np.arctan2(p[1], p[0]))
    if abs(a) < 12:
        return "straight ahead"
    if abs(a) < 35:
        return "slightly to the left" if a > 0 else "slightly to the right"
    return "to the left" if a > 0 else "to the right"


def _range(d) -> str:
    return "very close" if d < 1.5 else "nearby" if d < 3.5 else "far ahead"


def _motion(p, v) -> str:
    s = np.linalg.norm(v)
    if s < 0.2:
        return "standing"
    toward = -np.dot(v, p) / max(np.linalg.norm(p), 1e-6) / s
    if toward > 0.6:
        return "walking towards you"
    if toward < -0.6:
        return "walking away"
    return "crossing your path from the left" if v[1] < 0 else "crossing your path from the right"


def _layout(walls) -> tuple[str, str]:
    left, right, ahead = walls
    if left < 2.0 and right < 2.0:
        long = "the walls are close on both sides in a narrow hallway"
        short = "narrow hallway with walls on both sides"
    elif left < 2.0 or right < 2.0:
        side = "left" if left < right else "right"
        long = f"there is a wall close on the {side} side"
        short = f"wall on the {side}"
    else:
        long = "the space is open and wide"
        short = "open space"
    if ahead < 3.0:
        long += " and a wall is ahead where the path turns"
        short += " with a corner ahead"
    return long, short


class TemplateCaptioner:
    """Offline stand-in for GPT-4o: long and short captions from templates over the privileged
    :class:`CaptionScene` (it ignores the pixels). Wording varies with ``variant`` so that the
    SCTE sees paraphrases."""

    def caption(self, image: np.ndarray | None, scene: CaptionScene | None = None, variant: int = 0) -> Caption:
        if scene is None:
            return Caption("", "", -1, ok=False, source="template")
        act = ACTIONS[scene.action]
        people = np.asarray(scene.people, np.float64).reshape(-1, 2)
        vel = np.asarray(scene.people_vel, np.float64).reshape(-1, 2)
        order = np.argsort(np.linalg.norm(people, axis=1)) if len(people) else np.zeros(0, int)
        descr = []
        for i in order[:2]:
            colour = COLOURS[int(scene.colours[i])]
            grp = int(scene.groups[i]) if len(scene.groups) else -1
            together = " in a group" if grp >= 0 else ""
            descr.append(f"a person in a {colour} shirt {_motion(people[i], vel[i])}{together} "
                         f"{_bearing(people[i])} {_range(np.linalg.norm(people[i]))}")
        n = len(people)
        count = _NUM[min(n, 10)]
        place = scene.context
        lay_long, lay_short = _layout(scene.walls)
        phrase = ACTION_PHRASES[act][variant % 2]
        if n == 0:
            ppl_long = "There are no people in view"
        else:
            ppl_long = (f"There {'is' if n == 1 else 'are'} {count} {'person' if n == 1 else 'people'} present, "
                        f"including " + " and ".join(descr))
        opening = ("In the provided image, the scenario involves" if variant % 2 == 0
                   else "In this view, the scenario is")
        safety = (f" Ensure to maintain a safe distance from the person in the {COLOURS[int(scene.colours[order[0]])]} shirt."
                  if n else " Ensure to keep a safe distance from the walls.")
        long = f"{opening} {place}. {ppl_long}. The pathway: {lay_long}. To navigate safely, you should {phrase}.{safety}"
        moving = sum(np.linalg.norm(vel, axis=1) > 0.2) if n else 0
        if n == 0:
            ppl_short = "No people"
        else:
            cols = " and ".join(dict.fromkeys(COLOURS[int(c)] for c in scene.colours[order[:2]]))
            ppl_short = f"{count.capitalize()} {'person' if n == 1 else 'people'} in {cols} shirts " + (
                "walking" if moving else "standing")
        short = f"{ppl_short} in {place}. {lay_short.capitalize()}."
        return Caption(long, short, int(scene.action), True, "template")


def action_from_text(text: str) -> int:
    """The high-level action a long caption asks for (index into :data:`ACTIONS`; -1 if none):
    the first action phrase after "should", else anywhere in the text."""
    t = text.lower()
    tail = t.split("should", 1)[1] if "should" in t else t
    rules = (("yield", ("yield", "give way", "stop", "wait", "slow down")),
             ("turn_left", ("turn left", "turn to the left", "turning left")),
             ("turn_right", ("turn right", "turn to the right", "turning right")),
             ("keep_right", ("keep right", "to the right", "keep to the right", "pass on the right")),
             ("keep_left", ("keep left", "to the left", "keep to the left", "pass on the left")),
             ("straight", ("straight", "continue", "keep going", "forward")))
    for part in (tail, t):
        best, pos = -1, len(part) + 1
        for name, keys in rules:
            for k in keys:
                i = part.find(k)
                if 0 <= i < pos:
                    best, pos = ACTIONS.index(name), i
        if best >= 0:
            return best
    return -1


def with_action(long: str, action: int) -> str | None:
    """T_l with its navigation-action phrase replaced by a phrase of ``action`` (index into
    :data:`ACTIONS`), the rest of the description kept: the counterfactual captions that teach
    the TSM to select by E_T. None when ``long`` holds no template action phrase (free text from
    a real VLM), because its action cannot be rewritten reliably."""
    target = ACTION_PHRASES[ACTIONS[int(action)]]
    for phrases in ACTION_PHRASES.values():
        for v, phrase in enumerate(phrases):
            if phrase in long:
                return long.replace(phrase, target[v])
    return None


class OpenAICaptioner:
    """Captions from an OpenAI-compatible ``/chat/completions`` endpoint (GPT-4o, vLLM, ...),
    through the social module's HTTP client
    (:class:`~splatsearch.social.convoi.vlm.OpenAICompatibleVLM`, with its retries and back-off)
    and this module's captioning prompt. Pass either ``base_url`` + ``model`` (+ ``api_key``,
    ``timeout`` s per attempt) or an existing client as ``vlm``. Never raises for network
    problems: ``Caption.ok`` is False."""

    def __init__(self, base_url: str | None = None, model: str | None = None, *, vlm: Any = None,
                 api_key: str | None = None, timeout: float = 30.0, max_tokens: int = 400):
        from ..convoi.vlm import OpenAICompatibleVLM

        if vlm is None:
            if not base_url or not model:
                raise ValueError("OpenAICaptioner needs base_url and model, or vlm=")
            vlm = OpenAICompatibleVLM(base_url, model, api_key=api_key, timeout=timeout, max_tokens=max_tokens)
        self.vlm = vlm
        self.max_tokens = int(max_tokens)

    def caption(self, image: np.ndarray, scene: CaptionScene | None = None) -> Caption:
        reply = self.vlm.complete(self.vlm.chat_body(image, CAPTION_PROMPT, max_tokens=self.max_tokens))
        if reply.content is None:
            return Caption("", "", -1, ok=False, source=f"openai: {reply.error}")
        return parse_caption_reply(reply.content, "openai")


def parse_caption_reply(text: str, source: str = "vlm") -> Caption:
    """A :class:`Caption` from a VLM reply: JSON ``{"long", "short"}`` (also inside a code
    fence), else the whole text as T_l and its first sentence as T_s."""
    import re

    m = re.search(r"\{.*\}", text, re.S)
    long = short = ""
    if m:
        try:
            obj = json.loads(m.group(0))
            long, short = str(obj.get("long", "")), str(obj.get("short", ""))
        except (ValueError, AttributeError):
            pass
    if not long:
        long = text.strip()
        short = long.split(".")[0]
    return Caption(long, short, action_from_text(long), bool(long), source)


@jax.jit
def _side_walls(field: DistanceField, pose) -> jax.Array:
    """(3,) wall distances (m) to the left, right and ahead of ``pose`` (3,)."""
    angles = pose[2] + jnp.asarray([np.pi / 2, -np.pi / 2, 0.0], F32)
    return _cast(field, pose[:2], angles, jnp.zeros((1, 2), F32), jnp.zeros(1, bool))[0]


def caption_scene(scn, pose: np.ndarray, people: np.ndarray, people_vel: np.ndarray, action: int) -> CaptionScene:
    """The :class:`CaptionScene` of scenario ``scn`` with the robot at ``pose`` (3,) world and the
    people at ``people`` (P, 2) / ``people_vel`` (P, 2) world (inactive rows are ignored): only
    people inside the camera's field of view, within range and in line of sight are described."""
    from ..convoi.perception import visible_people

    pose = np.asarray(pose, np.float32)
    caps, valid = scn.padded_capsules()
    act = np.asarray(scn.peds.active)
    vis = np.asarray(visible_people(jnp.asarray(pose), jnp.asarray(people, F32), jnp.asarray(act),
                                    jnp.asarray(caps), jnp.asarray(valid), MAX_RANGE))
    pr = world_to_robot(np.asarray(people, np.float64), pose.astype(np.float64))
    in_fov = np.abs(np.arctan2(pr[:, 1], pr[:, 0])) < 0.5 * HFOV
    sel = np.flatnonzero(vis & in_fov)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    vr = np.asarray(people_vel, np.float64) @ np.array([[c, -s], [s, c]])
    gid = np.full(len(act), -1)
    for g, members in enumerate(scn.groups):
        gid[list(members)] = g
    tw = np.asarray(_side_walls(scn.field(), jnp.asarray(pose)))
    return CaptionScene(scn.context, scn.description, scn.seed, pr[sel], vr[sel],
                        np.array([person_colour(i, scn.seed) for i in sel], np.int64), gid[sel],
                        (float(tw[0]), float(tw[1]), float(tw[2])), int(action))
