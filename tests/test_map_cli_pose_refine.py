"""`splatsearch map` with the ground-robot tracking options: planar tracking, keyframe pose
refinement and per-frame exposure, on a tiny simulator walk."""

import json

import numpy as np

from splatsearch.cli import main


def test_map_track_planar_pose_refine_exposure(tmp_path):
    out = tmp_path / "map"
    rc = main(["map", "--seed", "1", "--frames", "6", "--width", "64", "--height", "48", "--iters", "4",
               "--keyframe-every", "1", "--track", "--odometry", "--track-iters", "5", "--track-planar",
               "--pose-refine", "--exposure", "--holdout-every", "0", "--out", str(out)])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_mapped"] == 6 and s["bad_frames"] == []
    assert s["train_keyframes_exposure"]["n"] == 6 and s["train_keyframes_exposure"]["psnr"] > 10
    assert np.isfinite(s["ate"]["rmse"]) and np.isfinite(s["ate_odometry"]["rmse"])
    # planar tracking and planar refinement keep the camera height of the first pose
    rows = np.loadtxt(out / "trajectory.txt")
    np.testing.assert_allclose(rows[:, 3], rows[0, 3], atol=1e-4)
