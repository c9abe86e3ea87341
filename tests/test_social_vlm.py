"""VLM clients (against a local stub server), reply parsing, record/replay and the rule-based VLM;
context classification and prompts."""

import base64
import itertools
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import ClassVar

import numpy as np
import pytest
from splatsearch.social.convoi.context import (
    CONTEXTS,
    PROMPT_TEMPLATE,
    CLIPContextClassifier,
    ModelUnavailable,
    RuleContextClassifier,
    behaviour_prompt,
)
from splatsearch.social.convoi.mmvm import Markers
from splatsearch.social.convoi.vlm import (
    MarkerScene,
    OpenAICompatibleVLM,
    ReplayVLM,
    RuleBasedVLM,
    VLMResult,
    parse_labels,
)

IMAGE = (np.random.default_rng(0).random((24, 32, 3))).astype(np.float32)


class Stub(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"  # keep-alive, as real API servers
    requests: ClassVar[list] = []
    counts: ClassVar[dict] = {}
    connections: ClassVar[int] = 0

    def setup(self):
        Stub.connections += 1
        super().setup()

    def log_message(self, *a):  # keep pytest output clean
        pass

    def _reply(self, code, body: str):
        data = body.encode()
        self.send_response(code)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def do_POST(self):
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        Stub.requests.append((self.path, dict(self.headers), body))
        mode = self.path.split("/")[1]
        Stub.counts[mode] = Stub.counts.get(mode, 0) + 1
        ok = json.dumps({"choices": [{"message": {"content": "Path: ```json\n[3, 5, 99, 3]\n```"}}]})
        if mode == "ok":
            self._reply(200, ok)
        elif mode == "slow":
            time.sleep(1.0)
            self._reply(200, ok)
        elif mode == "garbage":
            self._reply(200, "<html>definitely not json")
        elif mode == "nonumbers":
            self._reply(200, json.dumps({"choices": [{"message": {"content": "I cannot see any numbers."}}]}))
        elif mode == "flaky":
            self._reply(500 if Stub.counts[mode] == 1 else 200, ok)
        elif mode == "bad":
            self._reply(400, json.dumps({"error": "bad request"}))
        elif mode == "busy":  # rate-limited once, with the wait the server asks for
            if Stub.counts[mode] == 1:
                data = b'{"error": "rate limited"}'
                self.send_response(429)
                self.send_header("Retry-After", "7")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)
            else:
                self._reply(200, ok)


@pytest.fixture(scope="module")
def server():
    srv = ThreadingHTTPServer(("127.0.0.1", 0), Stub)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    yield f"http://127.0.0.1:{srv.server_address[1]}"
    srv.shutdown()
    srv.server_close()


def client(server, mode, **kw):
    kw.setdefault("timeout", 2.0)
    kw.setdefault("backoff", 0.01)
    return OpenAICompatibleVLM(f"{server}/{mode}/v1", "stub-model", api_key="sk-test", **kw)


def test_openai_client_success_sends_image_and_prompt(server):
    res = client(server, "ok").select_labels(IMAGE, "Pick numbers.", [1, 3, 5, 7])
    assert res.ok and res.labels == (3, 5) and res.source == "openai" and res.latency_s > 0
    path, headers, body = Stub.requests[-1]
    assert path == "/ok/v1/chat/completions" and headers["Authorization"] == "Bearer sk-test"
    assert body["model"] == "stub-model"
    parts = body["messages"][0]["content"]
    assert "Pick numbers." in parts[0]["text"] and "1, 3, 5, 7" in parts[0]["text"]
    png = base64.b64decode(parts[1]["image_url"]["url"].split(",", 1)[1])
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_openai_client_timeout_gives_ok_false(server):
    before = Stub.counts.get("slow", 0)
    res = client(server, "slow", timeout=0.2, retries=1).select_labels(IMAGE, "p", [3, 5])
    err = res.error.lower()
    assert not res.ok and ("timed out" in err or "timeout" in err), res.error
    # the client gave up on each attempt (the server answers only after 1 s): two attempts, both sent
    assert Stub.counts["slow"] - before == 2


def test_openai_client_garbage_and_empty_replies_give_ok_false(server):
    res = client(server, "garbage").select_labels(IMAGE, "p", [3, 5])
    assert not res.ok and "not JSON" in res.error
    res = client(server, "nonumbers").select_labels(IMAGE, "p", [3, 5])
    assert not res.ok and "no valid marker" in res.error
    res = OpenAICompatibleVLM("http://127.0.0.1:9/v1", "m", timeout=0.5, retries=0).select_labels(IMAGE, "p", [1])
    assert not res.ok and "request failed" in res.error  # nothing listens on port 9


def test_openai_client_retries_server_errors_but_not_client_errors(server):
    res = client(server, "flaky", retries=2).select_labels(IMAGE, "p", [3, 5])
    assert res.ok and Stub.counts["flaky"] == 2
    res = client(server, "bad", retries=3).select_labels(IMAGE, "p", [3, 5])
    assert not res.ok and "HTTP 400" in res.error and Stub.counts["bad"] == 1


def test_openai_client_keeps_its_connection_alive(server):
    with client(server, "ok") as vlm:
        vlm.select_labels(IMAGE, "p", [3, 5])
        before = Stub.connections
        for _ in range(3):
            assert vlm.select_labels(IMAGE, "p", [3, 5]).ok
        assert Stub.connections == before  # three more queries, no new connection


def test_openai_client_waits_what_retry_after_asks_up_to_a_cap(server):
    waits = []
    res = client(server, "busy", retries=2, backoff=0.01, sleep=waits.append).select_labels(IMAGE, "p", [3, 5])
    assert res.ok and Stub.counts["busy"] == 2 and waits == [7.0]
    Stub.counts["busy"] = 0
    waits.clear()
    capped = client(server, "busy", retries=2, max_retry_after=2.0, sleep=waits.append)
    assert capped.select_labels(IMAGE, "p", [3, 5]).ok and waits == [2.0]
    from splatsearch.social.convoi.vlm import retry_after_seconds

    assert retry_after_seconds("1.5") == 1.5 and retry_after_seconds(None) is None
    assert retry_after_seconds("Wed, 21 Oct 2015 07:28:00 GMT") == 0.0 and retry_after_seconds("soon") is None


def test_parse_labels_is_defensive():
    assert parse_labels("[4, 2, 9]", [2, 4]) == (4, 2)
    assert parse_labels('{"numbers": ["7", 3]}', [3, 7]) == (7, 3)
    assert parse_labels("Go 1 then 12, then 1 again and 3.5", [1, 12, 3]) == (1, 12)
    assert parse_labels("I refuse", [1, 2]) == ()
    assert parse_labels(None, [1]) == ()


def test_replay_records_atomically_and_replays_without_the_model(tmp_path):
    class Counting:
        calls = 0

        def select_labels(self, image, prompt, valid, scene=None):
            Counting.calls += 1
            return VLMResult(True, (valid[-1],), "[x]", None, 0.5, "fake")

    path = tmp_path / "rec" / "vlm.json"
    rec = ReplayVLM(str(path), Counting(), mode="record")
    assert rec.select_labels(IMAGE, "prompt A", [1, 2]).labels == (2,)
    assert rec.select_labels(IMAGE, "prompt B", [1, 2, 3]).labels == (3,)
    assert Counting.calls == 2 and path.exists()
    assert not list(path.parent.glob(".vlm-*"))  # no temporary file left behind
    data = json.loads(path.read_text())
    assert data["version"] == 1 and len(data["entries"]) == 2
    replay = ReplayVLM(str(path), mode="replay")
    r = replay.select_labels(IMAGE, "prompt B", [1, 2, 3])
    assert r.ok and r.labels == (3,) and r.source == "replay" and Counting.calls == 2
    miss = replay.select_labels(IMAGE, "prompt C", [1])
    assert not miss.ok and "not in the recording" in miss.error
    with pytest.raises(FileNotFoundError):
        ReplayVLM(str(tmp_path / "none.json"), mode="replay")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="cannot read"):
        ReplayVLM(str(tmp_path / "bad.json"))


def markers_3x5():
    xs, ys = np.meshgrid([1.0, 2.0, 3.0], [0.8, 0.4, 0.0, -0.4, -0.8], indexing="ij")
    xy = np.stack([xs.ravel(), ys.ravel()], -1)
    n = len(xy)
    return Markers(np.arange(1, n + 1), xy, np.zeros((n, 2), np.int64), np.zeros((n, 2)),
                   np.repeat(np.arange(3), 5), np.tile(np.arange(5), 3))


def test_rule_based_vlm_follows_the_behaviour_phrase():
    m = markers_3x5()
    scene = MarkerScene(m, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64), np.array([5.0, 0.0]),
                        lambda p: np.full(len(p), 1.0))
    vlm = RuleBasedVLM()
    straight = vlm.select_labels(IMAGE, behaviour_prompt("an open indoor space"), m.labels, scene)
    assert straight.ok and np.allclose(m.lookup(straight.labels)[:, 1], 0.0)
    right = vlm.select_labels(IMAGE, behaviour_prompt("an indoor corridor"), m.labels, scene)
    assert right.ok and (m.lookup(right.labels)[:, 1] < -0.3).all()
    # a standing pair right ahead: the path must not pass between them
    pair = np.array([[2.0, 0.45], [2.0, -0.45]])
    scene2 = MarkerScene(m, pair, np.zeros((2, 2)), np.array([0, 0]), np.array([5.0, 0.0]), lambda p: np.full(len(p), 1.0))
    res = vlm.select_labels(IMAGE, behaviour_prompt("people standing in groups"), m.labels, scene2)
    pts = np.vstack([[0.0, 0.0], m.lookup(res.labels)])
    crosses_gap = any((a[0] < 2.0 <= b[0]) and abs(a[1] + (b[1] - a[1]) * (2.0 - a[0]) / (b[0] - a[0])) < 0.45
                      for a, b in itertools.pairwise(pts))
    assert res.ok and not crosses_gap
    assert not vlm.select_labels(IMAGE, "p", m.labels, None).ok
    assert not vlm.select_labels(IMAGE, "p", [], scene).ok


def test_prompts_and_the_context_table():
    p = behaviour_prompt("people standing in groups")
    assert p.startswith("You are navigating a robot in this scenario.")
    assert p.endswith(CONTEXTS["people standing in groups"] + ".")
    assert "{behaviour}" in PROMPT_TEMPLATE
    with pytest.raises(ValueError, match="unknown context"):
        behaviour_prompt("a swimming pool")


@pytest.mark.parametrize("name,expected", [("hallway", "an indoor corridor"),
                                           ("static_groups", "people standing in groups"),
                                           ("crossing", "an open indoor space"),
                                           ("blind_corner", "an indoor corridor")])
def test_rule_context_classifier_on_the_scenarios(name, expected):
    from splatsearch.social.convoi.pipeline import CoNVOI
    from splatsearch.social.convoi.runner import make_world
    from splatsearch.social.convoi.scenarios import make_scenario

    scn = make_scenario(name, 0)
    obs = CoNVOI(RuleBasedVLM()).observe(scn.start, scn.peds, make_world(scn, "convoi"))
    res = RuleContextClassifier().classify(None, obs.scene)
    assert res.label == expected, res.features
    assert abs(sum(res.probs.values()) - 1.0) < 1e-9 and max(res.probs, key=res.probs.get) == expected


def test_blind_corner_is_recognised_near_the_corner():
    from splatsearch.social.convoi.pipeline import CoNVOI
    from splatsearch.social.convoi.runner import make_world
    from splatsearch.social.convoi.scenarios import make_scenario

    scn = make_scenario("blind_corner", 0)
    obs = CoNVOI(RuleBasedVLM()).observe(np.array([3.5, 0.0, 0.0]), scn.peds, make_world(scn, "convoi"))
    assert RuleContextClassifier().classify(None, obs.scene).label == "a blind corner in a corridor"


def test_paved_check_and_clip_adapter_errors(tmp_path):
    clf = RuleContextClassifier()
    assert clf.is_paved(np.full((8, 8, 3), 0.7, np.float32))
    grass = np.zeros((8, 8, 3), np.float32)
    grass[..., 1] = 0.6
    grass[..., 0] = 0.2
    assert not clf.is_paved(grass)
    with pytest.raises(FileNotFoundError, match="never downloaded"):
        CLIPContextClassifier(str(tmp_path / "missing.pt"))
    weights = tmp_path / "clip.pt"
    weights.write_bytes(b"0")
    try:
        CLIPContextClassifier(str(weights))
    except ModelUnavailable as e:
        assert "pip install" in str(e)  # open_clip / torch are not installed here
    with pytest.raises(ValueError, match="needs the scene"):
        clf.classify(None, None)
