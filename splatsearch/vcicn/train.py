"""Training the VCICN (:mod:`splatsearch.search.completion`) on shards of :mod:`splatsearch.vcicn.data`.

optax AdamW with warm-up and cosine decay, gradient clipping; a validation pass over held-apart
houses every ``eval_every`` steps, which also writes the run's checkpoint atomically
(``checkpoint.msgpack``: parameters, optimiser state, step, best score, log) and, on improvement,
the best weights (``best.npz``). A rerun with the same ``--out`` resumes from the checkpoint.
Training ends at ``steps``, when the validation loss has not improved for ``patience`` passes
(early stopping), or when ``max_minutes`` of wall time are spent. Nothing here is CPU-specific:
the same command runs on a GPU when JAX has one.

Augmentation, per object: the views are shuffled (the first view, the cameras' reference,
changes), and the cameras are dropped (zero features) for 20 % of the objects so the model also
works when an inpainter is called without cameras.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from dataclasses import asdict, dataclass

import numpy as np

from splatsearch.search.completion import (
    CAM_FEATURES,
    VCICNConfig,
    build_model,
    init_params,
    loss_fn,
    prepare_views,
    relative_cameras,
    save_weights,
)

from .data import list_shards, parse_houses, shard_seed


@dataclass(frozen=True)
class TrainConfig:
    """Training settings (steps, objects per batch, learning rate, model size in pixels, U-Net
    width, validation period in steps, early-stopping patience in validation passes, wall-time
    budget in minutes, seed, validation houses as a ``parse_houses`` string or None for the seeds
    ending in 9, camera-dropout probability, hole threshold on the stored 8-bit alpha, weight of
    the image-gradient L1 term of :func:`~splatsearch.search.completion.loss_fn`, and a weights
    ``.npz`` to start from instead of a random initialisation, see :func:`warm_start`)."""

    steps: int = 6000
    batch: int = 2
    lr: float = 2e-3
    width: int = 64
    height: int = 48
    features: int = 16
    eval_every: int = 400
    patience: int = 6
    max_minutes: float = 60.0
    seed: int = 0
    val_houses: str | None = None
    camera_dropout: float = 0.2
    alpha_tau: float = 0.5
    grad_weight: float = 0.0
    init: str | None = None


def parse_size(text: str) -> tuple[int, int]:
    """``"64x48"`` -> (64, 48)."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError as e:
        raise ValueError(f"size must be WxH in pixels, e.g. 64x48; got {text!r}") from e
    VCICNConfig(width=w, height=h)  # validates
    return w, h


@dataclass
class ObjectSet:
    """Training objects at the model's size: x (O, V, h, w, 4), hole (O, V, h, w), gt (O, V, h, w, 3),
    raw (O, V, h, w, 3) the render resized (holes left as rendered), viewmats (O, V, 4, 4),
    valid (O, V), seeds (O,)."""

    x: np.ndarray
    hole: np.ndarray
    gt: np.ndarray
    raw: np.ndarray
    viewmats: np.ndarray
    valid: np.ndarray
    seeds: np.ndarray

    def __len__(self) -> int:
        return len(self.x)


def load_objects(paths: list[str], width: int, height: int, alpha_tau: float = 0.5) -> ObjectSet:
    """Read shards and resize every view to the model's size (see :func:`prepare_views`)."""
    import cv2

    xs, holes, gts, raws, vms, valids, seeds = [], [], [], [], [], [], []
    for p in paths:
        with np.load(p) as z:
            render, alpha, gt, viewmats, valid = z["render"], z["alpha"], z["gt"], z["viewmats"], z["valid"]
        for o in range(len(render)):
            img = render[o].astype(np.float32) / 255.0
            mask = alpha[o] < alpha_tau * 255.0
            x, hole = prepare_views(img, mask, width, height)
            xs.append(x)
            holes.append(hole)
            gts.append(np.stack([cv2.resize(g.astype(np.float32) / 255.0, (width, height), interpolation=cv2.INTER_AREA)
                                 for g in gt[o]]))
            raws.append(np.stack([cv2.resize(r, (width, height), interpolation=cv2.INTER_AREA) for r in img]))
            vms.append(viewmats[o])
            valids.append(valid[o])
            seeds.append(shard_seed(p))
    if not xs:
        raise ValueError(f"no objects in {len(paths)} shard(s)")
    return ObjectSet(np.stack(xs), np.stack(holes), np.stack(gts), np.stack(raws), np.stack(vms),
                     np.stack(valids), np.array(seeds))


def warm_start(params, path: str, cfg: VCICNConfig):
    """``params`` (of architecture ``cfg``) with the weights of the file ``path``: every layer
    must have the same shape except the bottleneck's position embedding ``pos``, which is
    resized bilinearly to ``cfg``'s token grid. The U-Net is convolutional, so weights trained at
    one resolution start a run at another (e.g. 64x48 -> 128x96). Raises ValueError for another
    U-Net width, attention size or a missing layer."""
    import jax

    from splatsearch.search.completion import _flatten, _unflatten, load_weights

    src, src_cfg, _meta = load_weights(path)
    if (src_cfg.features, src_cfg.heads, src_cfg.blocks) != (cfg.features, cfg.heads, cfg.blocks):
        raise ValueError(f"cannot start from {path!r}: its architecture {src_cfg} differs from {cfg} "
                         "in more than the resolution")
    flat_src, flat_dst = _flatten(src), _flatten(jax.tree_util.tree_map(np.asarray, dict(params)))
    if set(flat_src) != set(flat_dst):
        raise ValueError(f"cannot start from {path!r}: its layers differ from this model's")
    out = {}
    for k, dst in flat_dst.items():
        w = flat_src[k]
        if w.shape != dst.shape:
            if k.split("/")[-1] != "pos":
                raise ValueError(f"cannot start from {path!r}: layer {k} is {w.shape}, the model's {dst.shape}")
            hs, ws = src_cfg.height // 8, src_cfg.width // 8
            hd, wd = cfg.height // 8, cfg.width // 8
            w = np.asarray(jax.image.resize(w.reshape(hs, ws, -1), (hd, wd, w.shape[-1]), "bilinear")).reshape(dst.shape)
        out[k] = w.astype(np.float32)
    return _unflatten(out)


def split_paths(paths: list[str], val_houses: str | None) -> tuple[list[str], list[str]]:
    """(train, validation) shards: validation = the seeds in ``val_houses`` or, by default, the
    seeds ending in 9."""
    val = set(parse_houses(val_houses)) if val_houses else None
    is_val = [(shard_seed(p) in val) if val is not None else shard_seed(p) % 10 == 9 for p in paths]
    tr = [p for p, v in zip(paths, is_val) if not v]
    va = [p for p, v in zip(paths, is_val) if v]
    if not tr or not va:
        raise ValueError(f"need training and validation houses; got {len(tr)} training and {len(va)} validation "
                         "shard(s) (validation: --val-houses, default the seeds ending in 9)")
    return tr, va


def make_batch(data: ObjectSet, idx: np.ndarray, rng: np.random.Generator | None, camera_dropout: float = 0.0):
    """A batch of objects ``idx`` as numpy arrays (x, cams, valid, hole, gt); with ``rng`` the
    valid views are shuffled and cameras dropped with probability ``camera_dropout``."""
    B, V = len(idx), data.valid.shape[1]
    x = np.zeros((B, V) + data.x.shape[2:], np.float32)
    hole = np.zeros((B, V) + data.hole.shape[2:], np.float32)
    gt = np.zeros((B, V) + data.gt.shape[2:], np.float32)
    cams = np.zeros((B, V, CAM_FEATURES), np.float32)
    valid = np.zeros((B, V), bool)
    for b, o in enumerate(idx):
        views = np.flatnonzero(data.valid[o])
        if rng is not None:
            views = rng.permutation(views)
        n = len(views)
        x[b, :n], hole[b, :n], gt[b, :n] = data.x[o, views], data.hole[o, views], data.gt[o, views]
        valid[b, :n] = True
        if rng is None or rng.random() >= camera_dropout:
            cams[b, :n] = relative_cameras(data.viewmats[o, views], n)
    return x, cams, valid, hole, gt


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of images in [0, 1], over ``mask`` pixels when given."""
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    mse = d.mean() if mask is None else d[np.asarray(mask, bool)].mean()
    return float(10 * np.log10(1.0 / max(mse, 1e-10)))


def _git_commit() -> str | None:
    try:
        here = os.path.dirname(os.path.abspath(__file__))
        return subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                              timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def train(data_dir: str, out_dir: str, cfg: TrainConfig | None = None, *, fresh: bool = False,
          export: str | None = None, command: str | None = None, progress: bool = True) -> dict:
    """Train (or resume) a VCICN; returns a summary (steps, best validation loss and metrics,
    minutes, why it stopped, paths). See the module docstring."""
    import jax
    import jax.numpy as jnp
    import optax
    from flax import serialization

    from splatsearch.io import atomic_write_bytes

    cfg = cfg or TrainConfig()
    mcfg = VCICNConfig(width=cfg.width, height=cfg.height, features=cfg.features)
    paths = list_shards(data_dir)
    tr_paths, va_paths = split_paths(paths, cfg.val_houses)
    t_load = time.perf_counter()
    tr = load_objects(tr_paths, cfg.width, cfg.height, cfg.alpha_tau)
    va = load_objects(va_paths, cfg.width, cfg.height, cfg.alpha_tau)
    t_load = time.perf_counter() - t_load
    os.makedirs(out_dir, exist_ok=True)
    ckpt_path, best_path = os.path.join(out_dir, "checkpoint.msgpack"), os.path.join(out_dir, "best.npz")

    model = build_model(mcfg)
    # The warm-up stays shorter than the run, so that even a 1-step run has a decay phase.
    warmup = min(500, cfg.steps // 10 + 1, cfg.steps - 1)
    sched = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, warmup, cfg.steps, cfg.lr * 0.05)
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(sched, weight_decay=1e-4))
    params = init_params(mcfg, cfg.seed)
    if cfg.init:
        params = jax.tree_util.tree_map(jnp.asarray, warm_start(params, cfg.init, mcfg))
    opt_state = opt.init(params)
    state = {"step": 0, "best": float("inf"), "best_step": 0, "bad_evals": 0, "log": [], "train_seconds": 0.0}
    if not fresh and os.path.exists(ckpt_path):
        with open(ckpt_path, "rb") as f:
            blob = serialization.msgpack_restore(f.read())
        if json.loads(blob["meta"])["model"] != asdict(mcfg):
            raise ValueError(f"checkpoint {ckpt_path!r} is of another architecture; use --fresh or another --out")
        params = serialization.from_state_dict(params, blob["params"])
        opt_state = serialization.from_state_dict(opt_state, blob["opt_state"])
        state = json.loads(blob["meta"])["state"]

    def loss_of(p, x, c, v, h, g):
        return loss_fn(model.apply(p, x, c, v), x, h, g, v, cfg.grad_weight)

    @jax.jit
    def step_fn(p, s, x, c, v, h, g):
        loss, grads = jax.value_and_grad(loss_of)(p, x, c, v, h, g)
        upd, s = opt.update(grads, s, p)
        return optax.apply_updates(p, upd), s, loss

    @jax.jit
    def eval_fn(p, x, c, v, h, g):
        return loss_of(p, x, c, v, h, g), model.apply(p, x, c, v)

    def validate(p) -> dict:
        losses, ps_c, ps_r = [], [], []
        for s in range(0, len(va), cfg.batch):
            idx = np.arange(s, min(len(va), s + cfg.batch))
            idx = np.concatenate([idx, np.full(cfg.batch - len(idx), idx[-1])])  # fixed shapes
            x, c, v, h, g = make_batch(va, idx, None)
            loss, pred = eval_fn(p, x, c, v, h, g)
            losses.append(float(loss))
            pred = np.asarray(pred)
            for b, o in enumerate(idx[:min(cfg.batch, len(va) - s)]):
                n = int(v[b].sum())
                comp = h[b, :n, ..., None] * pred[b, :n] + (1 - h[b, :n, ..., None]) * x[b, :n, ..., :3]
                ps_c.append(psnr(comp, g[b, :n]))
                ps_r.append(psnr(va.raw[o, :n], g[b, :n]))
        return {"loss": float(np.mean(losses)), "psnr": float(np.mean(ps_c)), "psnr_raw": float(np.mean(ps_r))}

    def checkpoint():
        blob = {"params": serialization.to_state_dict(params), "opt_state": serialization.to_state_dict(opt_state),
                "meta": json.dumps({"model": asdict(mcfg), "train": asdict(cfg), "state": state})}
        atomic_write_bytes(ckpt_path, serialization.msgpack_serialize(blob))

    rng = np.random.default_rng([cfg.seed, state["step"]])
    t0 = time.perf_counter()
    spent0 = state["train_seconds"]
    stop = "steps"
    bar = None
    if progress:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        bar = Progress(TextColumn("vcicn train"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
                       TimeElapsedColumn())
        bar.start()
        task = bar.add_task("steps", total=cfg.steps, completed=state["step"], info="")
    run_loss = []
    try:
        while state["step"] < cfg.steps:
            idx = rng.integers(0, len(tr), cfg.batch)
            x, c, v, h, g = make_batch(tr, idx, rng, cfg.camera_dropout)
            params, opt_state, loss = step_fn(params, opt_state, x, c, v, h, g)
            state["step"] += 1
            run_loss.append(float(loss))
            minutes = (time.perf_counter() - t0) / 60
            if bar:
                bar.update(task, completed=state["step"], info=f"loss {np.mean(run_loss[-50:]):.4f} "
                                                               f"best val {state['best']:.4f} {minutes:.1f} min")
            last = state["step"] >= cfg.steps or minutes >= cfg.max_minutes
            if state["step"] % cfg.eval_every == 0 or last:
                m = validate(params)
                m.update(step=state["step"], train_loss=float(np.mean(run_loss)), minutes=spent0 / 60 + minutes)
                run_loss = []
                state["log"].append(m)
                if m["loss"] < state["best"]:
                    state.update(best=m["loss"], best_step=state["step"], bad_evals=0, best_metrics=m)
                    save_weights(best_path, params, mcfg, meta={"step": state["step"], "val": m})
                else:
                    state["bad_evals"] += 1
                state["train_seconds"] = spent0 + time.perf_counter() - t0
                checkpoint()
                atomic_write_bytes(os.path.join(out_dir, "log.json"), json.dumps(state["log"], indent=1).encode())
                if state["bad_evals"] >= cfg.patience:
                    stop = "early stopping"
                    break
            if minutes >= cfg.max_minutes:
                stop = "wall-time budget"
                break
    finally:
        if bar:
            bar.stop()
    result = {"steps": state["step"], "best_step": state["best_step"], "best_val": state.get("best_metrics"),
              "stopped": stop, "train_minutes": state["train_seconds"] / 60, "load_seconds": t_load,
              "train_objects": len(tr), "val_objects": len(va),
              "train_houses": sorted({int(s) for s in tr.seeds}), "val_houses": sorted({int(s) for s in va.seeds}),
              "best": best_path, "checkpoint": ckpt_path}
    if export:
        from splatsearch.search.completion import load_weights

        params_b, _c, meta = load_weights(best_path)
        prov = {"data": os.path.abspath(data_dir), "data_shards": [os.path.basename(p) for p in paths],
                "train_houses": result["train_houses"], "val_houses": result["val_houses"],
                "command": command, "commit": _git_commit(), "train": asdict(cfg),
                "steps": state["step"], "best_step": state["best_step"], "stopped": stop,
                "train_minutes": round(result["train_minutes"], 2), "validation": state.get("best_metrics"),
                "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, jax {jax.__version__} on "
                           f"{jax.default_backend()}"}
        result["export_sha256"] = save_weights(export, params_b, mcfg, meta=meta, provenance=prov)
        result["export"] = export
    return result
