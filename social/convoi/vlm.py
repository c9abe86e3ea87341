"""The large-VLM interface of CoNVOI (eq 4): ``select_labels(image, prompt, valid) -> VLMResult``.

Implementations:

* :class:`OpenAICompatibleVLM`: any OpenAI-compatible ``/chat/completions`` endpoint (GPT-4o,
  Gemini through its OpenAI endpoint, vLLM, llama.cpp server, ...) over one keep-alive ``httpx``
  client: timeouts, retries with backoff on network errors, 429 and 5xx (waiting what the
  server's ``Retry-After`` asks, up to a cap), and defensive parsing of the
  reply. It never raises for a failed query: the result has ``ok=False`` and the planner falls
  back to plain DWA.
* :class:`RuleBasedVLM`: an offline stand-in that reads the behaviour phrase in the prompt and
  picks markers from the scene geometry (see its doc).
* :class:`ReplayVLM`: record the answers of another VLM to a JSON file (atomic writes), or replay
  them later without it, keyed by a hash of (image, prompt, valid labels).
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, NamedTuple, Protocol, runtime_checkable

import cv2
import numpy as np

from splatsearch.io import atomic_write_bytes


@dataclass(frozen=True)
class VLMResult:
    """ok: a usable answer; labels: the chosen marker numbers in path order (M_ref); raw: the
    model's text; error: why not ok; latency_s: wall-clock seconds of the query; source: which
    implementation answered."""

    ok: bool
    labels: tuple[int, ...] = ()
    raw: str = ""
    error: str | None = None
    latency_s: float = 0.0
    source: str = ""


@runtime_checkable
class VLM(Protocol):
    def select_labels(self, image: np.ndarray, prompt: str, valid: Sequence[int], scene: Any = None) -> VLMResult: ...


_INT = re.compile(r"(?<![\d.])\d{1,4}(?![\d.])")


def parse_labels(text: str, valid: Sequence[int]) -> tuple[int, ...]:
    """The marker numbers in a model reply, in order, without repeats, keeping only ``valid`` ones.

    Accepts a JSON list (also inside a ```json fence or an object such as {"numbers": [...]}) or
    free text ("Numbers: 3, 7 and 12"); a JSON list found anywhere wins over loose numbers.
    """
    if not isinstance(text, str):
        return ()
    valid_set = {int(v) for v in valid}
    nums: list[int] = []
    for m in re.finditer(r"\[[^\[\]]*\]", text):
        try:
            arr = json.loads(m.group(0))
        except (ValueError, TypeError):
            continue
        if isinstance(arr, list) and arr and all(isinstance(x, (int, float, str)) for x in arr):
            cand = []
            for x in arr:
                try:
                    cand.append(int(float(x)))
                except (ValueError, TypeError):
                    cand = []
                    break
            if cand:
                nums = cand
                break
    if not nums:
        nums = [int(m.group(0)) for m in _INT.finditer(text)]
    out: list[int] = []
    for n in nums:
        if n in valid_set and n not in out:
            out.append(n)
    return tuple(out)


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB image (uint8, or float in [0, 1])."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., :3][..., ::-1]))
    if not ok:
        raise ValueError("could not encode the image as PNG")
    return buf.tobytes()


class OpenAICompatibleVLM:
    """Client of an OpenAI-compatible chat-completions endpoint.

    Args:
        base_url: e.g. "https://api.openai.com/v1" or "http://127.0.0.1:8000/v1".
        model: the model name the server expects.
        api_key: the key, or None to read the environment variable ``api_key_env``.
        timeout: seconds per HTTP attempt; retries: extra attempts after the first;
        backoff: seconds before the first retry, doubled each time.
        max_tokens, temperature: generation settings.
    """

    def __init__(self, base_url: str, model: str, *, api_key: str | None = None, api_key_env: str = "OPENAI_API_KEY",
                 timeout: float = 20.0, retries: int = 2, backoff: float = 0.5, max_tokens: int = 200,
                 temperature: float = 0.0, max_retry_after: float = 30.0, sleep=time.sleep):
        if not base_url.startswith(("http://", "https://")):
            raise ValueError(f"base_url must start with http:// or https://, got {base_url!r}")
        if timeout <= 0 or retries < 0 or backoff < 0 or max_retry_after < 0:
            raise ValueError("need timeout > 0, retries >= 0, backoff >= 0 and max_retry_after >= 0")
        self.url = base_url.rstrip("/") + "/chat/completions"
        self.model = model
        self.api_key = api_key if api_key is not None else os.environ.get(api_key_env)
        self.timeout, self.retries, self.backoff = float(timeout), int(retries), float(backoff)
        self.max_retry_after = float(max_retry_after)
        self.max_tokens, self.temperature = int(max_tokens), float(temperature)
        self._sleep = sleep
        self._client = None  # one httpx.Client for every query: its connections are kept alive

    def close(self) -> None:
        """Close the kept-alive connections (a later query opens new ones)."""
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self) -> dict:  # picklable for worker processes: the connection pool stays behind
        return {**self.__dict__, "_client": None}

    def request_body(self, image: np.ndarray, prompt: str, valid: Sequence[int]) -> dict:
        """The JSON body sent for one marker query."""
        text = (f"{prompt} Valid numbers: {', '.join(str(int(v)) for v in valid)}. "
                "Answer with a JSON list of numbers in the order the robot should visit them, e.g. [3, 8, 12].")
        return self.chat_body(image, text)

    def chat_body(self, image: np.ndarray, text: str, max_tokens: int | None = None) -> dict:
        """The JSON body of one chat completion: ``text`` and ``image`` (H, W, 3) as a PNG."""
        b64 = base64.b64encode(encode_png(image)).decode("ascii")
        return {"model": self.model, "temperature": self.temperature,
                "max_tokens": self.max_tokens if max_tokens is None else int(max_tokens),
                "messages": [{"role": "user", "content": [
                    {"type": "text", "text": text},
                    {"type": "image_url", "image_url": {"url": f"data:image/png;base64,{b64}"}}]}]}

    def _post(self, body: bytes) -> tuple[int, str, float | None]:
        """(status, reply text, Retry-After seconds or None) of one POST."""
        import httpx

        if self._client is None:
            self._client = httpx.Client(timeout=self.timeout)
        headers = {"Content-Type": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        resp = self._client.post(self.url, content=body, headers=headers)
        return resp.status_code, resp.text, retry_after_seconds(resp.headers.get("Retry-After"))

    def complete(self, body: dict) -> ChatReply:
        """POST one chat-completion ``body`` with the retries and back-off; never raises for
        network or reply problems (``ChatReply.content`` is None and ``error`` says why)."""
        import httpx

        t0 = time.perf_counter()
        data = json.dumps(body).encode("utf-8")
        err = "no attempt made"
        wait = 0.0
        for attempt in range(self.retries + 1):
            if attempt:
                self._sleep(wait)
            wait = self.backoff * 2 ** attempt
            try:
                status, text, retry_after = self._post(data)
            except (httpx.HTTPError, OSError, ValueError) as e:
                kind = "timed out" if isinstance(e, httpx.TimeoutException) else type(e).__name__
                err = f"request failed: {kind}: {e}"
                continue
            if status == 429 or status >= 500:
                err = f"HTTP {status}: {text[:200]}"
                if retry_after is not None:  # the server said how long; never past the cap
                    wait = min(max(retry_after, 0.0), self.max_retry_after)
                continue
            if status != 200:
                return ChatReply(None, text[:2000], f"HTTP {status}: {text[:200]}", time.perf_counter() - t0)
            content, why = _content_of(text)
            if content is None:
                return ChatReply(None, text[:2000], why, time.perf_counter() - t0)
            return ChatReply(content, content[:2000], "", time.perf_counter() - t0)
        return ChatReply(None, "", err, time.perf_counter() - t0)

    def select_labels(self, image: np.ndarray, prompt: str, valid: Sequence[int], scene: Any = None) -> VLMResult:
        """Query the endpoint; never raises for network or reply problems (``ok=False``)."""
        valid = [int(v) for v in valid]
        if not valid:
            return VLMResult(False, error="no valid markers to choose from", source="openai")
        reply = self.complete(self.request_body(image, prompt, valid))
        if reply.content is None:
            return VLMResult(False, raw=reply.raw, error=reply.error, latency_s=reply.latency_s, source="openai")
        labels = parse_labels(reply.content, valid)
        if not labels:
            return VLMResult(False, raw=reply.raw, error="the reply names no valid marker", latency_s=reply.latency_s,
                             source="openai")
        return VLMResult(True, labels, reply.raw, None, reply.latency_s, "openai")


def retry_after_seconds(value: str | None) -> float | None:
    """Seconds asked by a ``Retry-After`` header: a number of seconds or an HTTP date (RFC 9110);
    None when absent or unreadable."""
    if not value:
        return None
    try:
        return float(value)
    except ValueError:
        pass
    from email.utils import parsedate_to_datetime

    try:
        when = parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())


class ChatReply(NamedTuple):
    """One chat completion: the message ``content`` (None on failure), the ``raw`` reply text
    (truncated), an ``error`` message ("" on success) and the latency in seconds."""

    content: str | None
    raw: str
    error: str
    latency_s: float


def _content_of(text: str) -> tuple[str | None, str]:
    try:
        obj = json.loads(text)
    except ValueError:
        return None, "the reply is not JSON"
    try:
        content = obj["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError):
        return None, "the reply has no choices[0].message.content"
    if isinstance(content, list):  # some servers return content parts
        content = " ".join(str(p.get("text", "")) if isinstance(p, dict) else str(p) for p in content)
    if not isinstance(content, str):
        return None, "the message content is not text"
    return content, ""


# ---------------------------------------------------------------------------------------------
# rule-based
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MarkerScene:
    """What :class:`RuleBasedVLM` sees besides the image (robot frame, metres, m/s).

    markers: :class:`splatsearch.social.convoi.mmvm.Markers`; people: (k, 2); people_vel: (k, 2);
    groups: (k,) labels (-1 alone); goal: (2,) the goal direction or point; clearance: callable
    mapping (n, 2) points to clearance (m) to the nearest obstacle (static or person).
    """

    markers: Any
    people: np.ndarray
    people_vel: np.ndarray
    groups: np.ndarray
    goal: np.ndarray
    clearance: Any = None


class RuleBasedVLM:
    """Offline stand-in for the large VLM.

    It reads the behaviour phrase of the prompt: "right" prefers markers on the right,
    "middle" prefers the most clearance, "group" forbids legs that pass between members of a group,
    "berth"/"away" widens the distance kept from people, "behind" penalises markers in front of
    walking people. Then, row by row from the nearest, it picks the cheapest valid marker
    (goal direction, the preferences above, smoothness between rows, predicted distance to people at
    the time the robot would get there at ``v_nominal``). Without a scene it cannot see anything
    and answers ``ok=False``.
    """

    def __init__(self, v_nominal: float = 0.5, berth: float = 1.0, wide_berth: float = 1.5):
        self.v_nominal, self.berth, self.wide_berth = float(v_nominal), float(berth), float(wide_berth)

    def select_labels(self, image: np.ndarray, prompt: str, valid: Sequence[int], scene: MarkerScene | None = None) -> VLMResult:
        t0 = time.perf_counter()
        if scene is None:
            return VLMResult(False, error="the rule-based VLM needs the marker scene", source="rules")
        p = prompt.lower()
        right = "right" in p
        middle = "middle" in p
        groups = "group" in p or "together" in p
        behind = "behind" in p
        berth = self.wide_berth if ("berth" in p or "away" in p) else self.berth
        m = scene.markers
        valid_set = {int(v) for v in valid}
        keep = np.array([int(k) in valid_set for k in m.labels], bool)
        if not keep.any():
            return VLMResult(False, error="no valid markers", latency_s=time.perf_counter() - t0, source="rules")
        ppl = np.asarray(scene.people, np.float64).reshape(-1, 2)
        pv = np.asarray(scene.people_vel, np.float64).reshape(-1, 2)
        grp = np.asarray(scene.groups).reshape(-1)
        pairs = [(a, b) for g in set(grp.tolist()) - {-1} for a in np.flatnonzero(grp == g)
                 for b in np.flatnonzero(grp == g) if a < b]
        goal = np.asarray(scene.goal, np.float64)
        # each group as a disc: its members' circle grown by a person radius and half a berth
        discs = []
        for g in set(grp.tolist()) - {-1}:
            mem = ppl[grp == g]
            c = mem.mean(0)
            discs.append((c, float(np.linalg.norm(mem - c, axis=1).max()) + 0.25 + 0.5 * berth))
        clear = scene.clearance(m.robot_xy) if scene.clearance is not None else np.full(len(m.labels), 1.0)
        chosen: list[int] = []
        prev = np.zeros(2)
        for row in sorted(set(m.row[keep].tolist())):
            idx = np.flatnonzero(keep & (m.row == row))
            pts = m.robot_xy[idx]
            ys = pts[:, 1]
            # lateral distance (m) from the straight line to the goal at each marker
            gdir = goal / max(np.linalg.norm(goal), 1e-6)
            cost = 1.0 * np.abs(pts[:, 0] * gdir[1] - pts[:, 1] * gdir[0])
            cost += 1.5 * np.abs(pts[:, 1] - prev[1])
            if right:
                cost += 4.0 * (ys - ys.min())
            if middle:
                cost += 3.0 * (1.0 - np.clip(clear[idx], 0, 1.0))
            cost += 4.0 * np.clip(0.5 - clear[idx], 0, None)
            t_arr = np.linalg.norm(pts, axis=1) / self.v_nominal
            for q, v in zip(ppl, pv):
                fut = q[None] + t_arr[:, None] * v[None]
                d = np.minimum(np.linalg.norm(pts - fut, axis=1), np.linalg.norm(pts - q[None], axis=1))
                cost += 6.0 * np.clip(berth - d, 0, None) ** 2
                if behind and np.linalg.norm(v) > 0.2:
                    ahead = (pts - q[None]) @ (v / np.linalg.norm(v))
                    cost += 2.0 * ((ahead > 0) & (ahead < 3.0) & (d < 2.0))
            if groups and pairs:
                for k, pt in enumerate(pts):
                    for a, b in pairs:
                        d, _ = _seg_seg(prev, pt, ppl[a], ppl[b])
                        if d < 0.35:
                            cost[k] = np.inf
                    for c, rad in discs:
                        # through the group's space now, or heading straight through it next
                        if _seg_point(prev, pt, c) < rad:
                            cost[k] += 6.0
                        if _seg_point(pt, goal, c) < rad:
                            cost[k] += 2.0
            if not np.isfinite(cost).any():
                break
            k = int(np.argmin(cost))
            chosen.append(int(m.labels[idx[k]]))
            prev = pts[k]
        if not chosen:
            return VLMResult(False, error="no acceptable marker", latency_s=time.perf_counter() - t0, source="rules")
        raw = json.dumps(chosen)
        return VLMResult(True, tuple(chosen), raw, None, time.perf_counter() - t0, "rules")


def _seg_point(a, b, p) -> float:
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0, 1)
    return float(np.linalg.norm(p - (a + t * ab)))


def _seg_seg(p1, p2, q1, q2) -> tuple[float, None]:
    """Distance between segments p1-p2 and q1-q2 (numpy, 2-D)."""
    def cross(u, v):
        return u[0] * v[1] - u[1] * v[0]

    d1, d2 = p2 - p1, q2 - q1
    o1, o2 = cross(d1, q1 - p1), cross(d1, q2 - p1)
    o3, o4 = cross(d2, p1 - q1), cross(d2, p2 - q1)
    if o1 * o2 < 0 and o3 * o4 < 0:
        return 0.0, None

    def ps(p, a, b):
        ab = b - a
        t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1)
        return float(np.linalg.norm(p - (a + t * ab)))

    return min(ps(p1, q1, q2), ps(p2, q1, q2), ps(q1, p1, p2), ps(q2, p1, p2)), None


# ---------------------------------------------------------------------------------------------
# record / replay
# ---------------------------------------------------------------------------------------------

def query_key(image: np.ndarray, prompt: str, valid: Sequence[int]) -> str:
    """sha256 of the image bytes (uint8 RGB), its shape, the prompt and the valid labels."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
    h = hashlib.sha256()
    h.update(str(img.shape).encode())
    h.update(np.ascontiguousarray(img).tobytes())
    h.update(prompt.encode("utf-8"))
    h.update(",".join(str(int(v)) for v in valid).encode())
    return h.hexdigest()


def atomic_write_json(path: str, obj) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (:func:`splatsearch.io.atomic_write_bytes`)."""
    atomic_write_bytes(path, json.dumps(obj, indent=1, sort_keys=True).encode("utf-8"))


@dataclass
class ReplayVLM:
    """Record or replay VLM answers.

    mode "record": ask ``inner`` and store every answer (ok or not) under its query key, writing
    the file atomically after each new answer; "replay": answer only from the file (a miss is
    ``ok=False``); "auto": replay when recorded, else record. The file is JSON:
    ``{"version": 1, "entries": {key: VLMResult fields + prompt}}``.
    """

    path: str
    inner: VLM | None = None
    mode: str = "auto"
    entries: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.mode not in ("record", "replay", "auto"):
            raise ValueError(f"mode must be 'record', 'replay' or 'auto', got {self.mode!r}")
        if self.mode == "record" and self.inner is None:
            raise ValueError("mode 'record' needs an inner VLM to ask")
        if os.path.exists(self.path):
            try:
                with open(self.path, encoding="utf-8") as f:
                    data = json.load(f)
            except (OSError, ValueError) as e:
                raise ValueError(f"cannot read the VLM recording {self.path!r}: {e}") from e
            if not isinstance(data, dict) or data.get("version") != 1 or not isinstance(data.get("entries"), dict):
                raise ValueError(f"{self.path!r} is not a VLM recording (version 1)")
            self.entries = dict(data["entries"])
        elif self.mode == "replay":
            raise FileNotFoundError(f"no VLM recording at {self.path!r}")

    def select_labels(self, image: np.ndarray, prompt: str, valid: Sequence[int], scene: Any = None) -> VLMResult:
        key = query_key(image, prompt, valid)
        if self.mode != "record" and key in self.entries:
            e = self.entries[key]
            return VLMResult(bool(e["ok"]), tuple(int(x) for x in e.get("labels", ())), e.get("raw", ""),
                             e.get("error"), float(e.get("latency_s", 0.0)), "replay")
        if self.mode == "replay" or self.inner is None:
            return VLMResult(False, error="query not in the recording", source="replay")
        res = self.inner.select_labels(image, prompt, valid, scene)
        entry = asdict(res)
        entry["labels"] = list(res.labels)
        entry["prompt"] = prompt
        self.entries[key] = entry
        atomic_write_json(self.path, {"version": 1, "entries": self.entries})
        return res
