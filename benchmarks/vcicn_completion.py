"""Completion quality of NVSM views on held-apart houses: raw render vs OpenCV vs VCICN.

For every object of the validation shards (training-range houses held apart from training,
never evaluation houses) the NVSM views stored by ``splatsearch vcicn data`` (160 x 120) are
completed and compared with the simulator's ground truth of the same cameras: PSNR over the whole
view and over the hole pixels, and SSIM (Gaussian window 11, sigma 1.5) over the whole view.

Completions:
  raw            the render as it is (holes black)
  opencv_nvsm    what the NVSM did before the VCICN: border-connected holes (background cut away
                 by the region crop) flat grey, enclosed holes OpenCV-Telea inpainted
  opencv_all     OpenCV Telea on every hole
  vcicn          the VCICN (shipped weights, or each --weights file) on every hole, with the views'
                 cameras; with --over also the same weights with composite="over" (the render's soft
                 pixels composited over the prediction, docs/vcicn.md)

PSNR is also reported over the covered pixels (not holes), which hole completion leaves as they
are unless the composite is "over".

Also times one NVSM run's completion (12 views at 320 x 240) for OpenCV and the VCICN.

    python benchmarks/vcicn_completion.py --data runs/vcicn_data [--weights shipped --weights W.npz]
        [--over] [--out R.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def ssim_np(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of two (H, W, 3) images in [0, 1] (Gaussian window 11, sigma 1.5)."""
    import cv2

    c1, c2 = 0.01 ** 2, 0.03 ** 2
    a, b = a.astype(np.float64), b.astype(np.float64)

    def g(x):
        return cv2.GaussianBlur(x, (11, 11), 1.5)

    ma, mb = g(a), g(b)
    va, vb, cov = g(a * a) - ma ** 2, g(b * b) - mb ** 2, g(a * b) - ma * mb
    s = ((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2))
    return float(s.mean())


def psnr(a, b, mask=None) -> float:
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    mse = d.mean() if mask is None else d[mask].mean()
    return float(10 * np.log10(1.0 / max(mse, 1e-10)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="runs/vcicn_data", help="folder of house_*.npz shards (default: runs/vcicn_data)")
    ap.add_argument("--weights", action="append", default=None,
                    help="VCICN weights .npz, or 'shipped' for the package's weights; repeat for several rows "
                         "(default: the shipped weights)")
    ap.add_argument("--over", action="store_true",
                    help="also score every weights file with composite='over' (soft covered pixels composited "
                         "over the prediction; default: off)")
    ap.add_argument("--val-houses", default=None, help="validation house seeds (default: the seeds ending in 9, "
                                                       "as in training)")
    ap.add_argument("--out", default=None, help="write the results as JSON here")
    args = ap.parse_args()

    from splatsearch.search.completion import VCICNInpainter
    from splatsearch.search.inpainting import OpenCVInpainter, split_holes
    from splatsearch.vcicn.data import list_shards
    from splatsearch.vcicn.train import split_paths

    _tr, va = split_paths(list_shards(args.data), args.val_houses)
    weights = args.weights or ["shipped"]
    models = {}
    for w in weights:
        name = "vcicn" if len(weights) == 1 else f"vcicn:{os.path.basename(w)}"
        path = None if w == "shipped" else w
        models[name] = VCICNInpainter(path)
        if args.over:
            models[name + ",over"] = VCICNInpainter(path, composite="over")
    vcicn = next(iter(models.values()))
    ocv = OpenCVInpainter()
    rows: dict[str, dict[str, list]] = {k: {"psnr": [], "psnr_holes": [], "psnr_covered": [], "ssim": []}
                                        for k in ("raw", "opencv_nvsm", "opencv_all", *models)}
    n_obj = n_views = 0
    hole_frac = []
    for p in va:
        z = np.load(p)
        for o in range(len(z["render"])):
            v = np.flatnonzero(z["valid"][o])
            img = z["render"][o, v].astype(np.float32) / 255
            gt = z["gt"][o, v].astype(np.float32) / 255
            alpha = z["alpha"][o, v].astype(np.float32) / 255
            holes = z["alpha"][o, v] < 128
            inner, outer = split_holes(holes)
            nv = img.copy()
            nv[outer] = 0.5
            outs = {"raw": img, "opencv_nvsm": ocv.inpaint(nv, inner), "opencv_all": ocv.inpaint(img, holes)}
            for name, m in models.items():
                outs[name] = m.inpaint(img, holes, viewmats=z["viewmats"][o, v], alpha=alpha)
            for k, out in outs.items():
                for i in range(len(v)):
                    rows[k]["psnr"].append(psnr(out[i], gt[i]))
                    if holes[i].any():
                        rows[k]["psnr_holes"].append(psnr(out[i], gt[i], holes[i]))
                    if (~holes[i]).any():
                        rows[k]["psnr_covered"].append(psnr(out[i], gt[i], ~holes[i]))
                    rows[k]["ssim"].append(ssim_np(out[i], gt[i]))
            n_obj += 1
            n_views += len(v)
            hole_frac.append(float(holes.mean()))
    res = {"objects": n_obj, "views": n_views, "houses": [os.path.basename(p) for p in va],
           "mean_hole_fraction": float(np.mean(hole_frac)), "weights": {k: m.source for k, m in models.items()},
           "metrics": {k: {m: float(np.mean(x)) for m, x in d.items()} for k, d in rows.items()}}
    # one NVSM run's completion: 12 views at the NVSM's 320 x 240
    rng = np.random.default_rng(0)
    imgs = rng.random((12, 240, 320, 3)).astype(np.float32)
    masks = rng.random((12, 240, 320)) < 0.3
    vms = np.tile(np.eye(4), (12, 1, 1))
    vcicn.inpaint(imgs, masks, viewmats=vms)  # compile
    t = time.perf_counter()
    for _ in range(3):
        vcicn.inpaint(imgs, masks, viewmats=vms)
    res["vcicn_ms_per_run"] = (time.perf_counter() - t) / 3 * 1000
    t = time.perf_counter()
    for _ in range(3):
        ocv.inpaint(imgs, masks)
    res["opencv_ms_per_run"] = (time.perf_counter() - t) / 3 * 1000
    res["load"] = os.getloadavg()[0]
    print(json.dumps(res, indent=1))
    print("\n| completion | PSNR dB (view) | PSNR dB (holes) | PSNR dB (covered) | SSIM |\n|---|---|---|---|---|")
    for k, d in res["metrics"].items():
        print(f"| {k} | {d['psnr']:.2f} | {d['psnr_holes']:.2f} | {d['psnr_covered']:.2f} | {d['ssim']:.3f} |")
    if args.out:
        from splatsearch.io import atomic_write_bytes

        atomic_write_bytes(args.out, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
