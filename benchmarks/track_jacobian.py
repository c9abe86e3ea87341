"""The tracker's analytic pose Jacobian against its forward-difference one, on a simulator and a TUM frame.

    python benchmarks/track_jacobian.py [--data sim,tum] [--seed 0] [--map-frames 6] [--frame 7]

For each data set a map is fitted with ground-truth poses to the first ``--map-frames`` frames
(simulator: dev house ``--seed`` at 320x240 with ``slam_eval.py``'s SIM settings; TUM: the shared
fr1/xyz frames at 320x240 with its REAL settings), then frame ``--frame`` is looked at from its
ground-truth pose. Three Jacobians of the residuals (rendered minus observed depth and colour)
w.r.t. the 6-DoF camera-frame increment are formed by :func:`splatsearch.slam.pose_jacobian`:
``analytic`` (one render), ``finite-difference`` (the tracker's: forward differences, step 1e-3)
and ``central`` (central differences of the same step, the reference). Printed, over the trusted
pixels:

- per column (w_x w_y w_z t_x t_y t_z) the relative error ||J - J_central|| / ||J_central|| of the
  analytic and forward-difference Jacobians, and the cosine between analytic and forward-difference;
- the relative error of the IRLS Gauss-Newton matrix (the metric the tracker uses) and the angle
  of its Gauss-Newton step against the reference's;
- how well each predicts the residuals' actual change for random pose increments of 1 and 5
  mrad / mm (relative L2 error of J xi against r(xi) - r(0)): the accuracy that matters to a step.

``analytic4`` is the analytic Jacobian with five-point image derivatives instead of central
differences. Also prints the load. Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
TUM = os.path.join(HERE, "..", "..", "shared", "data", "tum_fr1_xyz_first10")
METHODS = ("analytic", "analytic4", "finite-difference", "central")


def _build(name: str, seed: int, n_map: int, frame: int):
    sys.path.insert(0, HERE)
    from slam_eval import REAL, SIM

    from splatsearch import datasets
    from splatsearch.mapper import Mapper, MapperConfig

    if name == "sim":
        seq, cfg = datasets.sim_walk(seed, max(n_map, frame + 1), 320, 240), SIM
    else:
        if not os.path.isdir(TUM):
            raise SystemExit(f"{TUM} not present")
        seq, cfg = datasets.load_sequence(TUM, downscale=2), REAL
    m = Mapper(seq.K, seq.width, seq.height, MapperConfig(**cfg))
    for f in seq.frames[:n_map]:
        m.update(f.rgb, f.depth, f.viewmat)
    return m, seq.frames[frame], seq.K, seq.width, seq.height


def compare(gmap, f, K, W, H, rng, label: str) -> dict:
    """Print and return the comparison at ``f``'s ground-truth pose."""
    import jax.numpy as jnp

    from splatsearch.slam import TrackerConfig, perturb_viewmat, pose_jacobian

    cfg = TrackerConfig()
    Js = {}
    for meth in METHODS:
        Js[meth], r, mask = pose_jacobian(gmap, f.rgb, f.depth, f.viewmat, K, W, H, meth.rstrip("4"),
                                          order=4 if meth.endswith("4") else 2)
    mb = mask > 0
    a = np.array([1.0, cfg.w_color, cfg.w_color, cfg.w_color])
    n = max(mb.sum(), 1)
    ar = np.abs(r)
    scale = (ar * mask[..., None]).sum((0, 1)) / n
    eps = np.array([cfg.gn_eps_depth] + [cfg.gn_eps_color] * 3)
    w = mask[..., None] * a / n / np.maximum(ar, np.maximum(eps, cfg.gn_eps_rel * scale))
    ref = Js["central"][mb]  # (N, 4, 6)
    out = {"label": label, "trusted": float(mask.mean())}
    print(f"== {label}: {W}x{H}, {gmap.n_active} Gaussians, trusted pixels {mask.mean():.3f}")
    for meth in METHODS[:3]:
        J = Js[meth][mb]
        col = [np.linalg.norm(J[..., j] - ref[..., j]) / np.linalg.norm(ref[..., j]) for j in range(6)]
        out[f"col_err_{meth}"] = col
        print(f"  {meth:17s} column rel. error vs central: " + " ".join(f"{c:.3f}" for c in col))
    ja, jf = Js["analytic"][mb], Js["finite-difference"][mb]
    cos = [float((ja[..., j] * jf[..., j]).sum() / np.linalg.norm(ja[..., j]) / np.linalg.norm(jf[..., j]))
           for j in range(6)]
    out["cos_analytic_fd"] = cos
    print("  cosine analytic vs forward-difference per column: " + " ".join(f"{c:.3f}" for c in cos))
    sgn = (a * mask[..., None] / n * np.sign(r))
    Hc = np.einsum("hwck,hwc,hwcl->kl", Js["central"], w, Js["central"])
    gc = np.einsum("hwck,hwc->k", Js["central"], sgn)
    dc = -np.linalg.solve(Hc, gc)
    for meth in METHODS[:3]:
        Hm = np.einsum("hwck,hwc,hwcl->kl", Js[meth], w, Js[meth])
        gm = np.einsum("hwck,hwc->k", Js[meth], sgn)
        dm = -np.linalg.solve(Hm, gm)
        he = np.linalg.norm(Hm - Hc) / np.linalg.norm(Hc)
        ang = np.degrees(np.arccos(np.clip(dm @ dc / np.linalg.norm(dm) / np.linalg.norm(dc), -1, 1)))
        out[f"metric_err_{meth}"], out[f"step_angle_{meth}"] = float(he), float(ang)
        print(f"  {meth:17s} Gauss-Newton metric rel. error {he:.3f}, step angle {ang:.2f} deg, "
              f"step norm ratio {np.linalg.norm(dm) / np.linalg.norm(dc):.3f}")
    # prediction of the actual change for random increments
    from splatsearch.gaussians import render_args
    from splatsearch.rasterization import rasterize

    margs = render_args(gmap.params(), gmap.active, gmap.isotropic)
    vm = jnp.asarray(f.viewmat, jnp.float32)
    for size in (1e-3, 5e-3):
        errs = {m: [] for m in METHODS}
        for _ in range(4):
            xi = rng.normal(size=6)
            xi = size * xi / np.linalg.norm(xi) * np.sqrt(2)  # about `size` rad and `size` m
            o = rasterize(*margs, perturb_viewmat(vm, jnp.asarray(xi, jnp.float32)), jnp.asarray(K, jnp.float32),
                          W, H, render_mode="RGB+D", validate=False)
            r1 = np.concatenate([np.asarray(o.depth) - f.depth[..., None], np.asarray(o.image) - f.rgb], -1)
            dr = (r1 - r)[mb] * np.sqrt(a)  # colour counted with the loss's weight
            for meth in METHODS:
                pred = (Js[meth][mb] @ xi) * np.sqrt(a)
                errs[meth].append(np.linalg.norm(pred - dr) / np.linalg.norm(dr))
        out[f"pred_err_{size:g}"] = {m: float(np.mean(v)) for m, v in errs.items()}
        print(f"  increments of {size * 1e3:g} mrad/mm: relative error of J xi vs the actual change: "
              + ", ".join(f"{m} {np.mean(v):.3f}" for m, v in errs.items()))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="sim,tum", help="comma-separated subset of sim,tum (default both)")
    ap.add_argument("--seed", type=int, default=0, help="dev house (default 0; never >= 1000)")
    ap.add_argument("--map-frames", type=int, default=6, help="frames mapped with ground-truth poses (default 6)")
    ap.add_argument("--frame", type=int, default=7, help="the frame looked at (default 7)")
    a = ap.parse_args(argv)
    if a.seed >= 1000:
        ap.error("seeds >= 1000 are evaluation houses: never tuned on")
    print(f"load {os.getloadavg()}")
    rng = np.random.default_rng(0)
    for name in a.data.split(","):
        m, f, K, W, H = _build(name, a.seed, a.map_frames, a.frame)
        compare(m.map, f, K, W, H, rng, f"{name} frame {a.frame}")
    print(f"load {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
