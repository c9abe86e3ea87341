"""Plug-in spec strings (splatsearch.plugins): parsing, the offline kinds, and every error path.

Runs without torch: real-model kinds are only constructed here (they load nothing until first
use); running them is tests/test_model_adapters.py (``pytest -m models``).
"""

from __future__ import annotations

import argparse
import pickle

import numpy as np
import pytest

from splatsearch.nav.encoders import ColorTextureEncoder, ImageEncoder
from splatsearch.plugins import (
    SPEC_HELP,
    PluginSpec,
    make_detector,
    make_encoder,
    make_inpainter,
    make_matcher,
    parse_spec,
)
from splatsearch.search import (
    DiffusionInpainter,
    Detector,
    Inpainter,
    LoFTRMatcher,
    Matcher,
    OpenCVInpainter,
    SIFTMatcher,
    SimDetector,
    UltralyticsDetector,
)
from splatsearch.sim.house import GOAL_CLASSES


def test_parse_spec_forms():
    assert parse_spec("sift") == PluginSpec("sift", None, {})
    assert parse_spec(" SIFT ") == PluginSpec("sift", None, {})
    ps = parse_spec("loftr:/w/loftr.ckpt,conf_thresh=0.3,max_side=480,model=none,device=cuda:0,fast=true")
    assert ps.kind == "loftr" and ps.path == "/w/loftr.ckpt"
    assert ps.options == {"conf_thresh": 0.3, "max_side": 480, "model": None, "device": "cuda:0", "fast": True}
    assert isinstance(ps.options["max_side"], int)
    assert parse_spec("yolo:/m/y.pt,sam=/m/mobile_sam.pt").options == {"sam": "/m/mobile_sam.pt"}
    assert parse_spec("diffusion:/p,prompt=a photo of a chair").options["prompt"] == "a photo of a chair"
    # a path keeps its own colons after the first
    assert parse_spec("yolo:/a:b/c.pt").path == "/a:b/c.pt"
    assert pickle.loads(pickle.dumps(ps)) == ps


@pytest.mark.parametrize("bad", ["", "  ", ",x=1", ":/path", "loftr:", "sift,ratio", "sift,=3",
                                 "sift,ratio=0.7,ratio=0.8"])
def test_parse_spec_rejects(bad):
    with pytest.raises(ValueError):
        parse_spec(bad)


def test_parse_spec_rejects_non_strings():
    with pytest.raises(TypeError, match="string"):
        parse_spec(SIFTMatcher())


def test_sim_detector_spec():
    d = make_detector("sim")
    assert isinstance(d, SimDetector) and isinstance(d, Detector)
    assert d.goal_classes == GOAL_CLASSES and d.min_pixels == SimDetector().min_pixels
    d = make_detector("sim,min_pixels=40", goal_classes=("chair",))
    assert d.goal_classes == ("chair",) and d.min_pixels == 40


def test_sift_matcher_spec_matches_agent_defaults():
    m = make_matcher("sift")
    assert isinstance(m, SIFTMatcher) and isinstance(m, Matcher)
    ref = SIFTMatcher()
    assert (m.ratio, m.ransac_thresh, m.min_matches, m.model, m.contrast_threshold) == \
        (ref.ratio, ref.ransac_thresh, ref.min_matches, ref.model, ref.contrast_threshold)
    # the agent's NVSM default
    assert make_matcher("sift", renders=True).contrast_threshold == SIFTMatcher.for_renders().contrast_threshold
    m = make_matcher("sift,contrast_threshold=0.03,ratio=0.8,model=homography", renders=True)
    assert (m.contrast_threshold, m.ratio, m.model) == (0.03, 0.8, "homography")
    with pytest.raises(ValueError, match="ratio"):
        make_matcher("sift,ratio=1.5")  # the class's own validation still applies


def test_opencv_inpainter_and_colortexture_encoder_specs():
    inp = make_inpainter("opencv,method=ns,radius=2")
    assert isinstance(inp, OpenCVInpainter) and isinstance(inp, Inpainter)
    assert (inp.method, inp.radius) == ("ns", 2.0)
    img = np.random.default_rng(0).random((1, 24, 32, 3)).astype(np.float32)
    mask = np.zeros((1, 24, 32), bool)
    mask[0, 8:12, 8:12] = True
    out = inp.inpaint(img, mask)
    np.testing.assert_array_equal(out[~mask], img[~mask])
    enc = make_encoder("colortexture,size=32")
    assert isinstance(enc, ColorTextureEncoder) and isinstance(enc, ImageEncoder) and enc.size == 32
    assert enc.embed(img[0]).shape == (enc.dim,)


def test_model_kinds_build_lazily_from_local_files(tmp_path):
    w = tmp_path / "yolo.pt"
    w.write_bytes(b"not read until first use")
    sam = tmp_path / "mobile_sam.pt"
    sam.write_bytes(b"")
    d = make_detector(f"yolo:{w},sam={sam},conf=0.5,imgsz=320,max_det=20", goal_classes=("tv_monitor", "chair"))
    assert isinstance(d, UltralyticsDetector) and isinstance(d, Detector)
    assert (d.weights_path, d.sam_weights_path, d.conf, d.imgsz, d.max_det) == (str(w), str(sam), 0.5, 320, 20)
    # only the goal classes survive the COCO map
    assert {v for v in d.class_map.values() if v is not None} == {"tv_monitor", "chair"}
    assert d.class_map["tv"] == "tv_monitor" and d.class_map["couch"] is None
    assert {v for v in make_detector(f"yolo:{w}").class_map.values() if v} == set(GOAL_CLASSES)

    m = make_matcher(f"loftr:{w},conf_thresh=0.2,model=none")
    assert isinstance(m, LoFTRMatcher) and m.conf_thresh == 0.2 and m.model is None
    assert make_matcher(f"loftr:{w}", renders=True).conf_thresh == 0.5  # its default; renders changes only SIFT

    pipe = tmp_path / "pipeline"
    pipe.mkdir()
    inp = make_inpainter(f"diffusion:{pipe},prompt=a chair,num_inference_steps=4,seed=3")
    assert isinstance(inp, DiffusionInpainter) and (inp.prompt, inp.steps, inp.seed) == ("a chair", 4, 3)


@pytest.mark.parametrize("factory,spec,err,match", [
    (make_detector, "detr:/x.pt", ValueError, "unknown detector kind 'detr'.*known: sim, yolo"),
    (make_detector, "yolo", ValueError, "needs a local path"),
    (make_detector, "sim:/x.pt", ValueError, "takes no path"),
    (make_detector, "sim,conf=0.3", ValueError, r"unknown option\(s\) \['conf'\].*allowed: min_pixels"),
    (make_detector, "yolo:/nonexistent/yolo.pt", FileNotFoundError, "never downloaded"),
    (make_matcher, "superglue", ValueError, "known: akaze, features, loftr, rootsift, sift, sift-essential"),
    (make_matcher, "loftr", ValueError, "needs a local path"),
    (make_matcher, "loftr:/nonexistent/loftr.ckpt", FileNotFoundError, "file not found"),
    (make_matcher, "sift,sam=/x", ValueError, "unknown option"),
    (make_inpainter, "lama:/x", ValueError, "known: auto, diffusion, opencv, vcicn"),
    (make_inpainter, "diffusion:/nonexistent/pipe", FileNotFoundError, "directory not found"),
    (make_encoder, "dino:/x", ValueError, "known: colortexture, openclip, transformers"),
    (make_encoder, "openclip:/nonexistent/clip.pt", FileNotFoundError, "file not found"),
    (make_encoder, "transformers:/nonexistent/dir", FileNotFoundError, "directory not found"),
])
def test_spec_errors(factory, spec, err, match):
    with pytest.raises(err, match=match):
        factory(spec)


def test_directory_kinds_reject_files(tmp_path):
    f = tmp_path / "model.bin"
    f.write_bytes(b"")
    with pytest.raises(FileNotFoundError, match="directory not found"):
        make_inpainter(f"diffusion:{f}")
    with pytest.raises(FileNotFoundError, match="file not found"):
        make_matcher(f"loftr:{tmp_path}")


def test_spec_help_works_as_argparse_help():
    for kind in ("sim", "yolo:", "sift", "loftr:", "opencv", "diffusion:", "colortexture", "openclip:",
                 "transformers:", "never downloaded"):
        assert kind in SPEC_HELP
    p = argparse.ArgumentParser()
    p.add_argument("--detector", default="sim", help=SPEC_HELP)
    assert "yolo:PATH" in p.format_help()  # argparse %-formats help: no stray '%'
    assert p.parse_args(["--detector", "yolo:/m/y.pt,sam=/m/s.pt"]).detector == "yolo:/m/y.pt,sam=/m/s.pt"


def test_building_model_kinds_imports_no_model_library(tmp_path):
    """Specs are checked in the parent process before workers start: that must stay cheap."""
    import subprocess
    import sys

    w = tmp_path / "w.pt"
    w.write_bytes(b"")
    code = (
        "import sys\n"
        "from splatsearch.plugins import make_detector, make_matcher, make_inpainter\n"
        f"make_detector('yolo:{w},sam={w}'); make_matcher('loftr:{w}'); make_inpainter('diffusion:{tmp_path}')\n"
        "heavy = [m for m in ('torch', 'kornia', 'ultralytics', 'diffusers', 'transformers') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]


def test_agent_builds_its_plugins_from_the_config_specs():
    import numpy as np

    from splatsearch.agent import AgentConfig, SplatSearchAgent
    from splatsearch.search.detection import SimDetector
    from splatsearch.search.matching import RENDER_CONTRAST_THRESHOLD, SIFTMatcher

    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    goal = np.full((48, 64, 3), 0.5, np.float32)
    a = SplatSearchAgent(K, 64, 48, goal, "chair", (0.0, 0.0, 0.0), config=AgentConfig(matcher="sift,ratio=0.7"))
    assert isinstance(a.perception.detector, SimDetector) and a.perception.detector.goal_classes == ("chair",)
    m, r = a.verifier.matcher, a.verifier.nvsm_matcher
    assert isinstance(m, SIFTMatcher) and isinstance(r, SIFTMatcher) and m is not r
    assert m.ratio == r.ratio == 0.7
    assert r.contrast_threshold == RENDER_CONTRAST_THRESHOLD != m.contrast_threshold
    mine = SIFTMatcher()
    b = SplatSearchAgent(K, 64, 48, goal, "chair", (0.0, 0.0, 0.0), matcher=mine)
    assert b.verifier.matcher is mine and b.verifier.nvsm_matcher is mine  # an explicit matcher scores renders too


def test_cli_plugin_flags_are_checked_before_anything_runs(tmp_path, capsys):
    from splatsearch.cli import main
    from splatsearch.evaluation import eval_title

    assert main(["eval", "--episodes", "1", "--detector", "yolo:/nonexistent/y.pt", "--out", str(tmp_path)]) == 2
    assert "/nonexistent/y.pt" in capsys.readouterr().err
    assert main(["demo", "--no-viewer", "--matcher", "surf", "--out", str(tmp_path)]) == 2
    assert "surf" in capsys.readouterr().err
    assert "oracle" in eval_title("val-hard", 50, 0) and "matcher sift" in eval_title("val-hard", 50, 0)
    assert "oracle" not in eval_title("val", 5, 0, agent_overrides={"detector": "yolo:/m.pt"})
