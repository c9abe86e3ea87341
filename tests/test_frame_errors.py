"""trajectory.frame_errors and slam_eval's per-frame error rows: where a walk's ATE comes from."""

import os
import sys

import numpy as np
from scipy.spatial.transform import Rotation

from splatsearch.trajectory import ate, frame_errors

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))


def _walk(n=12):
    """A ground robot's world-to-camera poses (z up): camera +z looks along the heading, moving forward."""
    out = []
    for k in range(n):
        yaw = 0.1 * k
        heading = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        c2w = np.eye(4)
        # camera axes: x right, y down, z forward
        c2w[:3, 2] = heading
        c2w[:3, 1] = [0, 0, -1]
        c2w[:3, 0] = np.cross(c2w[:3, 1], heading)
        c2w[:3, 3] = [0.3 * k, 0.05 * k * k, 1.0]
        out.append(np.linalg.inv(c2w))
    return np.array(out)


def test_rigid_copy_has_no_error_and_rms_is_ate():
    gt = _walk()
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    T[:3, 3] = [2.0, -1.0, 0.0]
    fe = frame_errors(gt @ np.linalg.inv(T), gt)
    assert np.abs(fe["error"]).max() < 1e-9 and np.abs(fe["yaw"]).max() < 1e-9
    # a perturbed copy: the RMS of the per-frame errors is the ATE
    rng = np.random.default_rng(0)
    est = gt.copy()
    est[:, :3, 3] += rng.normal(0, 0.02, (len(gt), 3))
    fe = frame_errors(est, gt)
    assert np.isclose(np.sqrt(np.mean(fe["error"] ** 2)), ate(est, gt)["rmse"])


def test_known_offset_along_across_and_yaw_with_a_given_alignment():
    gt = _walk()
    est = gt.copy()
    k = 5
    c2w = np.linalg.inv(gt[k])
    heading = c2w[:3, 2]
    left = np.cross([0, 0, 1.0], heading)
    c2w[:3, 3] += 0.03 * heading - 0.02 * left   # 3 cm ahead, 2 cm to the right
    c2w[:3, :3] = Rotation.from_euler("z", 2, degrees=True).as_matrix() @ c2w[:3, :3]  # 2 deg to the left
    est[k] = np.linalg.inv(c2w)
    fe = frame_errors(est, gt, alignment=(np.eye(3), np.zeros(3)))
    assert np.isclose(fe["along"][k], 0.03) and np.isclose(fe["across"][k], -0.02)
    assert np.isclose(np.degrees(fe["yaw"][k]), 2.0)
    others = np.arange(len(gt)) != k
    assert np.abs(fe["error"][others]).max() < 1e-12
    # a non-finite estimate is NaN, not an error
    est[2] = np.nan
    fe = frame_errors(est, gt)
    assert np.isnan(fe["error"][2]) and np.isfinite(fe["error"][others & (np.arange(len(gt)) != 2)]).all()


def test_slam_eval_rows_use_the_final_alignment_for_the_tracked_pose(tmp_path):
    import slam_eval

    gt = _walk(6)
    est = gt.copy()
    trk = gt.copy()
    c2w = np.linalg.inv(trk[3])
    c2w[:3, 3] += 0.01 * c2w[:3, 2]  # the tracker had frame 3 1 cm ahead; the refinement fixed it
    trk[3] = np.linalg.inv(c2w)
    pf = [{"frame": 2 * k, "status": "mapped", "f2f": "accepted",
           "track_viewmat": trk[k].ravel().tolist() if k else None} for k in range(6)]
    rows = slam_eval.frame_error_rows({"timing": {"per_frame": pf}}, est, gt)
    assert [r["frame"] for r in rows] == [0, 2, 4, 6, 8, 10]
    assert max(r["error_cm"] for r in rows) < 1e-6
    assert np.isclose(rows[3]["track_along_cm"], 1.0) and np.isclose(rows[3]["track_error_cm"], 1.0)
    path = tmp_path / "frame_errors.tsv"
    slam_eval.write_frame_errors(str(path), rows)
    lines = path.read_text().splitlines()
    assert lines[0].split("\t") == list(slam_eval.FRAME_ERROR_COLUMNS) and len(lines) == 7


def test_f2f_scan_link_detail_projects_on_the_odometry_direction():
    import f2f_scan

    def step(dz, yaw_deg):  # a camera moving dz m forward (+z) and turning about its -y (up) axis
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_rotvec(np.radians(yaw_deg) * np.array([0, -1.0, 0])).as_matrix()
        c2w[:3, 3] = [0, 0, dz]
        return np.linalg.inv(c2w)

    up = np.array([0, -1.0, 0])
    d = f2f_scan.link_detail(step(0.103, 1.0), step(0.110, 1.5), step(0.100, 1.2), up)
    assert np.isclose(d["odo_along"], 0.110) and np.isclose(d["true_along"], 0.100) and np.isclose(d["cv_along"], 0.103)
    assert np.isclose(np.degrees(d["cv_yaw"]), 1.0) and np.isclose(np.degrees(d["odo_yaw"]), 1.5)
    assert np.isclose(np.degrees(d["true_yaw"]), 1.2)
    failed = f2f_scan.link_detail(None, step(0.110, 1.5), step(0.100, 1.2), up)
    assert failed["cv_along"] is None and failed["cv_yaw"] is None
