"""Dataset loaders: TUM on the shared real frames, and tiny fixtures of the Replica, ScanNet,
7-Scenes and generic-folder layouts written from those frames (from synthetic frames when the
shared data is absent)."""

import json
import os

import cv2
import numpy as np
import pytest

from splatsearch import datasets
from splatsearch.datasets import detect_format, load_sequence
from splatsearch.datasets.tum import quat_to_R
from splatsearch.trajectory import rotation_to_quat

TUM = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "tum_fr1_xyz_first10")
HAVE_TUM = os.path.isdir(TUM)
needs_tum = pytest.mark.skipif(not HAVE_TUM, reason=f"shared TUM frames not present at {TUM}")
N = 3
FX, FY, CX, CY = 517.3, 516.5, 318.6, 255.3


def _source():
    """N frames: (rgb uint8 BGR (480, 640, 3), depth metres (480, 640), camera-to-world (4, 4))."""
    if HAVE_TUM:
        seq = datasets.load_tum(TUM, max_frames=N, undistort=False)
        names = sorted(os.listdir(os.path.join(TUM, "rgb")))[:N]
        bgr = [cv2.imread(os.path.join(TUM, "rgb", n)) for n in names]
        return [(b, f.depth, np.linalg.inv(f.viewmat.astype(np.float64))) for b, f in zip(bgr, seq.frames)]
    rng = np.random.default_rng(0)
    out = []
    for i in range(N):
        c2w = np.eye(4)
        c2w[:3, 3] = [0.01 * i, 0.0, 0.0]
        d = np.full((480, 640), 1.5, np.float32)
        d[:40] = 0.0
        out.append((rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), d, c2w))
    return out


@pytest.fixture(scope="module")
def source():
    return _source()


def _mm(d):
    return np.round(d * 1000).astype(np.uint16)


def _check_like_source(seq, source, depth_tol=0.0011):
    assert len(seq) == N and (seq.width, seq.height) == (640, 480)
    for f, (bgr, d, c2w) in zip(seq.frames, source):
        assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.float32
        np.testing.assert_allclose(f.depth, d, atol=depth_tol)
        np.testing.assert_allclose(np.linalg.inv(f.viewmat.astype(np.float64)), c2w, atol=1e-5)
        # jpg is lossy: the mean colour is what survives exactly enough
        assert abs(f.rgb.mean() - bgr.mean() / 255) < 0.02


def write_replica(root, source):
    res = root / "results"
    res.mkdir(parents=True)
    for i, (bgr, d, _) in enumerate(source):
        cv2.imwrite(str(res / f"frame{i:06d}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, 98])
        cv2.imwrite(str(res / f"depth{i:06d}.png"), np.round(d * 6553.5).astype(np.uint16))
    (root / "traj.txt").write_text("".join(" ".join(f"{v:.10f}" for v in c2w.reshape(-1)) + "\n"
                                           for _, _, c2w in source))
    (root / "cam_params.json").write_text(json.dumps(
        {"camera": {"w": 640, "h": 480, "fx": FX, "fy": FY, "cx": CX, "cy": CY, "scale": 6553.5}}))
    return root


def write_scannet(root, source):
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True)
    for i, (bgr, d, c2w) in enumerate(source):
        # ScanNet's colour is larger than its depth (1296x968 vs 640x480); here 2x
        cv2.imwrite(str(root / "color" / f"{i}.jpg"), cv2.resize(bgr, (1280, 960)), [cv2.IMWRITE_JPEG_QUALITY, 98])
        cv2.imwrite(str(root / "depth" / f"{i}.png"), _mm(d))
        np.savetxt(root / "pose" / f"{i}.txt", c2w)
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = FX, FY, CX, CY
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", K)
    return root


def write_7scenes(root, source):
    seq = root / "seq-01"
    seq.mkdir(parents=True)
    for i, (bgr, d, c2w) in enumerate(source):
        cv2.imwrite(str(seq / f"frame-{i:06d}.color.png"), bgr)
        dm = _mm(d)
        dm[d == 0] = 65535  # 7-Scenes marks invalid depth with 65535
        cv2.imwrite(str(seq / f"frame-{i:06d}.depth.png"), dm)
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", c2w)
    return root


def write_folder(root, source, pose_style="matrix"):
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    lines = []
    for i, (bgr, d, c2w) in enumerate(source):
        cv2.imwrite(str(root / "rgb" / f"{i:04d}.png"), bgr)
        cv2.imwrite(str(root / "depth" / f"{i:04d}.png"), _mm(d))
        if pose_style == "matrix":
            lines.append(" ".join(f"{v:.10f}" for v in c2w.reshape(-1)))
        else:
            q = rotation_to_quat(c2w[:3, :3])
            lines.append(f"{100 + i:.3f} " + " ".join(f"{v:.10f}" for v in [*c2w[:3, 3], *q]))
    (root / "poses.txt").write_text("\n".join(lines) + "\n")
    (root / "intrinsics.json").write_text(json.dumps({"fx": FX, "fy": FY, "cx": CX, "cy": CY, "depth_scale": 1000}))
    return root


@needs_tum
def test_tum_loader_on_real_frames():
    seq = load_sequence(TUM)
    assert seq.format == "tum" and len(seq) == 10 and seq.has_gt
    raw = load_sequence(TUM, max_frames=1, undistort=False)
    # the project's K has pixel centres at +0.5: TUM's (OpenCV) principal point moves by half a pixel
    np.testing.assert_allclose(raw.K, [[FX, 0, CX + 0.5], [0, FY, CY + 0.5], [0, 0, 1]], rtol=1e-6)
    assert any("distortion" in n for n in seq.notes)
    # undistorted frames are zoomed to hold only what the sensor saw: no empty border
    assert seq.K[0, 0] > FX and seq.K[1, 1] > FY
    assert (seq.frames[0].depth[:, :3] > 0).any() and (seq.frames[0].depth[-3:] > 0).any()
    assert not np.allclose(raw.frames[0].rgb, seq.frames[0].rgb)
    d = seq.frames[0].depth
    assert 0.3 < np.median(d[d > 0]) < 3.0 and (d == 0).any()  # real sensor: holes
    c = np.array([np.linalg.inv(f.viewmat)[:3, 3] for f in seq.frames])
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert (steps < 0.05).all() and steps.sum() > 0.005  # 30 Hz: millimetres to centimetres a frame
    # ground truth is interpolated at the rgb timestamp, not the nearest line
    from splatsearch.datasets.tum import read_list

    gt = np.array([[t] + [float(v) for v in vals] for t, vals in read_list(os.path.join(TUM, "groundtruth.txt"))])
    k = np.searchsorted(gt[:, 0], seq.timestamps[0])
    a = (seq.timestamps[0] - gt[k - 1, 0]) / (gt[k, 0] - gt[k - 1, 0])
    np.testing.assert_allclose(c[0], (1 - a) * gt[k - 1, 1:4] + a * gt[k, 1:4], atol=1e-5)
    half = load_sequence(TUM, "tum", max_frames=2, downscale=2)
    assert (half.width, half.height) == (320, 240) and half.frames[0].depth.shape == (240, 320)
    np.testing.assert_allclose(half.K[:2], seq.K[:2] / 2, rtol=1e-6)


@needs_tum
def test_tum_errors_and_missing_ground_truth(tmp_path):
    import shutil

    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    shutil.copytree(TUM, root)
    for p in (root, root / "rgb", root / "depth"):
        os.chmod(p, 0o755)
    os.chmod(root / "groundtruth.txt", 0o644)
    os.chmod(root / "intrinsics.json", 0o644)
    os.remove(root / "intrinsics.json")  # the folder name selects the fr1 calibration
    seq = load_sequence(str(root), max_frames=2, undistort=False)
    np.testing.assert_allclose(seq.K[0, 0], FX)
    assert any("fr1" in n for n in seq.notes)
    os.remove(root / "groundtruth.txt")
    with pytest.raises(FileNotFoundError, match="groundtruth.txt"):
        load_sequence(str(root))
    unposed = load_sequence(str(root), require_poses=False, max_frames=2)
    assert not unposed.has_gt and unposed.frames[0].viewmat is None


@pytest.mark.parametrize("layout", ["replica", "scannet", "7scenes", "folder", "folder_tum_poses"])
def test_each_layout_loads_its_fixture(tmp_path, source, layout):
    writer = {"replica": write_replica, "scannet": write_scannet, "7scenes": write_7scenes,
              "folder": write_folder, "folder_tum_poses": lambda r, s: write_folder(r, s, "tum")}[layout]
    root = writer(tmp_path / layout, source)
    fmt = layout.split("_")[0]
    assert detect_format(str(root)) == fmt
    seq = load_sequence(str(root))
    assert seq.format == fmt
    tol = 1 / 6553.5 + 1e-6 if fmt == "replica" else 0.0006
    _check_like_source(seq, source, depth_tol=tol)
    if fmt != "7scenes":  # 7-Scenes has one fixed calibration
        np.testing.assert_allclose(seq.K, [[FX, 0, CX + 0.5], [0, FY, CY + 0.5], [0, 0, 1]], rtol=1e-6)
    if layout == "folder_tum_poses":
        np.testing.assert_allclose(seq.timestamps, [100, 101, 102])
    two = load_sequence(str(root), fmt, max_frames=2, downscale=2)
    assert len(two) == 2 and two.frames[1].rgb.shape == (240, 320, 3)


def test_7scenes_invalid_depth_and_scene_folder(tmp_path, source):
    root = write_7scenes(tmp_path / "chess", source)
    seq = load_sequence(str(root))  # a scene folder with one seq-XX
    assert seq.path.endswith("seq-01")
    d0 = source[0][1]
    assert np.all(seq.frames[0].depth[d0 == 0] == 0)  # 65535 -> invalid
    (root / "seq-02").mkdir()
    with pytest.raises(ValueError, match="seq-XX"):
        load_sequence(str(root), "7scenes")


def test_scannet_lost_pose_becomes_nan(tmp_path, source):
    root = write_scannet(tmp_path / "scene0000_00", source)
    np.savetxt(root / "pose" / "1.txt", np.full((4, 4), -np.inf))
    seq = load_sequence(str(root))
    assert np.isnan(seq.frames[1].viewmat).all() and np.isfinite(seq.frames[0].viewmat).all()
    assert any("no valid ground-truth pose" in n for n in seq.notes)


def test_clear_errors(tmp_path, source):
    # missing pose file, naming it
    root = write_replica(tmp_path / "replica", source)
    os.remove(root / "traj.txt")
    with pytest.raises(FileNotFoundError, match="traj.txt"):
        load_sequence(str(root))
    assert not load_sequence(str(root), require_poses=False).has_gt
    root = write_folder(tmp_path / "folder", source)
    os.remove(root / "poses.txt")
    with pytest.raises(FileNotFoundError, match="poses.txt"):
        load_sequence(str(root))
    # a depth image of the wrong size, naming the file
    root = write_7scenes(tmp_path / "7s", source)
    bad = root / "seq-01" / "frame-000001.depth.png"
    cv2.imwrite(str(bad), np.zeros((240, 320), np.uint16))
    with pytest.raises(ValueError, match=r"frame-000001\.depth\.png.*320x240, expected 640x480"):
        load_sequence(str(root))
    # an unknown layout, a missing folder, an unknown format name, a malformed pose file
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "a.txt").write_text("x")
    with pytest.raises(ValueError, match="unknown RGB-D layout"):
        load_sequence(str(tmp_path / "junk"))
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_sequence(str(tmp_path / "nowhere"))
    with pytest.raises(ValueError, match="unknown format"):
        load_sequence(str(tmp_path / "junk"), "kitti")
    root = write_replica(tmp_path / "replica2", source)
    (root / "traj.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="16 numbers"):
        load_sequence(str(root))
    root = write_folder(tmp_path / "folder2", source)
    (root / "intrinsics.json").write_text('{"fx": 1}')
    with pytest.raises(ValueError, match="intrinsics.json"):
        load_sequence(str(root))


def test_quaternion_helpers_agree():
    from scipy.spatial.transform import Rotation

    for R in Rotation.random(20, random_state=1).as_matrix():
        np.testing.assert_allclose(quat_to_R(rotation_to_quat(R)), R, atol=1e-9)


def test_sim_walk_odometry_drifts_from_ground_truth():
    from splatsearch.datasets import noisy_odometry

    rng = np.random.default_rng(0)
    poses = np.cumsum(np.c_[0.1 * np.ones(50), 0.02 * rng.normal(size=50), 0.05 * np.ones(50)], 0)
    exact = noisy_odometry(poses, 0.0, 0.0)
    np.testing.assert_allclose(exact[:, :2], poses[:, :2], atol=1e-9)
    noisy = noisy_odometry(poses, 0.05, 0.01, seed=1)
    np.testing.assert_allclose(noisy[0], poses[0])
    err = np.linalg.norm(noisy[:, :2] - poses[:, :2], axis=1)
    assert err[-1] > err[5] > 0  # drift grows


def test_map_command_on_a_dataset_writes_ate_trajectory_and_timing(tmp_path, source):
    from splatsearch.cli import main
    from splatsearch.trajectory import read_tum

    root = write_folder(tmp_path / "folder", source)
    out = tmp_path / "out"
    base = ["map", "--data", str(root), "--downscale", "4", "--iters", "2", "--holdout-every", "0"]
    assert main(base + ["--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["format"] == "folder" and s["frames_mapped"] == N and not s["tracking"]
    assert s["ate"]["rmse"] < 1e-4 and s["ate"]["n"] == N  # ground-truth poses: nothing to align away
    assert s["timing"]["median_map_s"] > 0 and s["timing"]["median_track_s"] is None
    assert [r["status"] for r in s["timing"]["per_frame"]] == ["first", "mapped", "mapped"]
    ts, vms = read_tum(str(out / "trajectory.txt"))
    assert len(ts) == N and len(s["trajectory_tum"]) == N
    np.testing.assert_allclose(np.linalg.inv(vms[1]), source[1][2], atol=1e-4)
    out2 = tmp_path / "out2"
    assert main(base + ["--track", "--track-iters", "3", "--out", str(out2)]) == 0
    s = json.loads((out2 / "summary.json").read_text())
    assert s["tracking"] and "ate" in s and s["timing"]["median_track_s"] > 0
    assert len(s["timing"]["per_frame"]) == N and "train_at_gt_pose" in s
    assert main(base + ["--track", "--track-from-gt", "--track-iters", "2", "--out", str(out2)]) == 0
    assert json.loads((out2 / "summary.json").read_text())["ate"]["n"] == N
    assert main(base + ["--track-from-gt", "--out", str(out2)]) == 2  # needs --track
    assert main(base + ["--pose-refine", "--track-planar", "--out", str(out2)]) == 2  # so do these
    # without ground truth, tracking still maps; ATE is not reported
    os.remove(root / "poses.txt")
    out3 = tmp_path / "out3"
    assert main(base + ["--track", "--track-iters", "2", "--out", str(out3)]) == 0
    s = json.loads((out3 / "summary.json").read_text())
    assert "ate" not in s and s["frames_mapped"] >= 1
    assert main(base + ["--out", str(out3)]) == 2  # no poses and no --track: a clear error


def test_map_command_bad_paths_give_one_line_errors(tmp_path, capsys):
    from splatsearch.cli import main

    assert main(["map", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "missing" in err and err.startswith("splatsearch: error:")
    (tmp_path / "junk").mkdir()
    assert main(["map", "--data", str(tmp_path / "junk"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown RGB-D layout" in err
    assert main(["map", "--data", str(tmp_path / "junk"), "--format", "replica", "--out", str(tmp_path / "o")]) == 2
    assert "results" in capsys.readouterr().err


@needs_tum
def test_map_command_tum_alias(tmp_path):
    from splatsearch.cli import main

    out = tmp_path / "o"
    assert main(["map", "--tum", TUM, "--frames", "2", "--downscale", "4", "--iters", "2", "--holdout-every", "0",
                 "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["format"] == "tum" and s["frames_mapped"] == 2 and s["resolution"] == [160, 120]


def test_warp_depth_moves_a_plane():
    from splatsearch.datasets.base import warp_depth

    K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
    d = np.full((48, 64), 2.0, np.float32)
    d[:, :4] = 0.0
    np.testing.assert_array_equal(warp_depth(d, K, np.eye(4)), d)
    back = np.eye(4)
    back[2, 3] = 0.5  # the target camera is 0.5 m behind: the plane is 2.5 m away, smaller in the image
    w = warp_depth(d, K, back)
    assert np.allclose(w[w > 0], 2.5) and 0.5 < np.mean(w > 0) < np.mean(d > 0)
    side = np.eye(4)
    side[0, 3] = 0.02  # 2 cm sideways at 2 m with f = 100: one pixel
    w = warp_depth(d, K, side)
    assert (w[:, 5] > 0).all() and (w[:, 4] == 0).all()
