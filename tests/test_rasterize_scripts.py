"""The benchmark scripts that need hardware or packages this machine lacks parse their arguments
and fail with a clear message instead of a traceback."""

import importlib.util
import os
import subprocess
import sys

import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..")


def _run(script, *args):
    return subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", script), *args], capture_output=True,
                          text=True, timeout=120)


def test_gpu_vs_gsplat_help():
    out = _run("gpu_vs_gsplat.py", "--help")
    assert out.returncode == 0
    assert "--scenes" in out.stdout and "gsplat" in out.stdout


def test_gpu_vs_gsplat_without_gpu_fails_cleanly():
    try:
        import torch  # noqa: F401

        has_cuda_torch = torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None
    except ImportError:
        has_cuda_torch = False
    if has_cuda_torch:
        pytest.skip("torch, CUDA and gsplat are present: the script would run the comparison")
    out = _run("gpu_vs_gsplat.py")
    assert out.returncode == 2
    assert "gpu_vs_gsplat:" in out.stderr and "Traceback" not in out.stderr


def test_vs_splax_help():
    out = _run("vs_splax.py", "--help")
    assert out.returncode == 0
    assert "splax==0.2.3" in out.stdout


def test_critical_path_help():
    out = _run("critical_path.py", "--help")
    assert out.returncode == 0
    assert "--scenes" in out.stdout and "critical path" in out.stdout


def test_cuda_pose_grad_check_help_and_without_gpu():
    out = _run("cuda_pose_grad_check.py", "--help")
    assert out.returncode == 0 and "--device" in out.stdout
    import jax

    if any(d.platform == "gpu" for d in jax.devices()):
        pytest.skip("a GPU is present: the script would run the check")
    out = _run("cuda_pose_grad_check.py", "--device", "cuda")
    assert out.returncode == 2
    assert "cuda_pose_grad_check: no cuda device" in out.stderr and "Traceback" not in out.stderr


def test_track_speed_and_profile_refuse_bad_arguments():
    out = _run("track_speed.py", "--data", "kitti")
    assert out.returncode == 2 and "--data" in out.stderr
    out = _run("track_speed.py", "--seed", "1000")
    assert out.returncode == 2 and "evaluation houses" in out.stderr
    out = _run("track_profile.py", "--size", "100x10")
    assert out.returncode == 2 and "--size" in out.stderr
