"""`splatsearch map` with the ground-robot tracking options: planar tracking, keyframe pose
refinement and per-frame exposure, on a tiny simulator walk."""

import json

import numpy as np
import pytest

from splatsearch.cli import main


def test_map_track_planar_pose_refine_exposure(tmp_path):
    out = tmp_path / "map"
    rc = main(["map", "--seed", "1", "--frames", "6", "--width", "64", "--height", "48", "--iters", "4",
               "--keyframe-every", "1", "--track", "--odometry", "--track-iters", "5", "--track-planar",
               "--pose-refine", "--exposure", "--holdout-every", "3", "--out", str(out)])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    # frames 1 and 4 are held out: observed for the frame-to-frame chain, never mapped
    assert s["frames_mapped"] == 4 and s["bad_frames"] == []
    assert s["train_keyframes_exposure"]["n"] == 4 and s["train_keyframes_exposure"]["psnr"] > 10
    assert np.isfinite(s["ate"]["rmse"]) and np.isfinite(s["ate_odometry"]["rmse"])
    # the frame-to-frame rotation prior (on by default with odometry) was tried on every tracked frame
    f2f = [r["f2f"] for r in s["timing"]["per_frame"][1:]]
    assert all(x in ("accepted", "rejected", "failed") for x in f2f), f2f
    assert sum(s["f2f"].values()) == 3
    # held-out views scored at their ground-truth poses and at poses tracked in the map
    assert s["held_out"]["n"] == 2 and s["held_out_tracked"]["n"] == 2
    # planar tracking and planar refinement keep the camera height of the first pose
    rows = np.loadtxt(out / "trajectory.txt")
    np.testing.assert_allclose(rows[:, 3], rows[0, 3], atol=1e-4)


def test_map_fast_tracking_flags(tmp_path):
    out = tmp_path / "map"
    base = ["map", "--seed", "1", "--frames", "4", "--width", "160", "--height", "128", "--iters", "4",
            "--holdout-every", "0", "--out", str(out)]
    # the tracking-only flags need --track
    assert main(base + ["--track-patience", "5"]) == 2
    assert main(base + ["--track-coarse-iters", "10"]) == 2
    assert main(base + ["--track-prior-lateral", "0.01"]) == 2
    with pytest.raises(SystemExit) as bad:  # argparse refuses it with its usage message
        main(base + ["--track", "--odometry", "--track-prior-lateral", "-1"])
    assert bad.value.code == 2
    rc = main(base + ["--track", "--odometry", "--track-solver", "adam", "--track-iters", "4", "--track-coarse-iters",
                      "6", "--track-patience", "3", "--track-prior-weight", "0.002", "--track-prior-lateral", "off"])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_mapped"] == 4 and s["bad_frames"] == []
    steps = [r["track_steps"] for r in s["timing"]["per_frame"] if r["track_steps"] is not None]
    # both stages ran (a stage runs at least 1 + patience steps, or all of them): 40x32 coarse, then 160x128
    assert len(steps) == 3 and all(5 <= n <= 10 for n in steps), steps
    assert s["timing"]["mean_track_cpu_s"] > 0
