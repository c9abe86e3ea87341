"""Training and evaluation of OLiVia-Nav (thesis 3.4, 3.5): checkpoints, the three training stages
with early stopping, and the forms of Tables I and II.

Stages (thesis 3.4): 1) SC-CLIP (eq 3), AdamW + cosine schedule; 2) the TPN (eq 2) on frozen E_I;
3) the TSM (eq 7) on the TPN's plans with k* from the captions' actions, plus counterfactual
captions (:func:`tsm_rows`). Each stage keeps the epoch with the lowest validation loss (early
stopping with ``patience``) and writes it as a checkpoint (atomically) whenever it improves.
Every jitted function sees one shape per stage (training batches drop the remainder,
validation is one batch or equal chunks, batched inference pads its last chunk), so each
compiles once: on 2 CPU cores compilation is a large part of a run.

Checkpoints are ``.npz`` files: one array per parameter leaf (``<net>/<path>``), the text database
D_T, and a JSON header (``__meta__``) holding the format name, the configurations and a SHA-256
digest over every array's name, dtype, shape and bytes. :func:`load_checkpoint` rejects a file
that is truncated, is not an npz, has the wrong format, or whose digest does not match.

Learning rates and epochs differ from the thesis (1e-4 / 8e-4 / 1e-5 over 100-500 epochs on an
H100) because a default run here must finish within 15 minutes on 2 CPU cores; they are in
:class:`TrainConfig`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import logging
import os
import time
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from splatsearch.io import atomic_write_bytes

from . import sc_clip, tpn, tsm
from .llu import LLUBuffer, LLUConfig, TextDB, add_view_entries, build_text_db, llu_update
from .planner import (
    VARIANT_LABELS,
    VARIANTS,
    OliviaConfig,
    OliviaNav,
    retrieve,
    run_olivia_episode,
)
from .captions import LONG_LEN, SHORT_LEN, TemplateCaptioner, with_action
from .baseline_cache import BaselineCache
from .dataset import HEADON_DOOR_SEEDS, Samples, build_dataset
from .features import action_of
from ..convoi.runner import REFERENCE
from ..convoi.scenario_names import DOOR_TRAIN_SEEDS, LLU_ADAPT_SEEDS, LLU_TEST_SEEDS
from ..convoi.scenarios import TABLE_ONE_SEEDS, THESIS_SCENARIOS, make_scenario
from .tokenizer import DEFAULT_TOKENIZER

logger = logging.getLogger(__name__)

FORMAT = "splatsearch-olivia-checkpoint"
VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint file is missing, corrupt or of the wrong format."""


# -- checkpoints ----------------------------------------------------------------------------------

def _flatten(tree, prefix: str) -> dict[str, np.ndarray]:
    out = {}
    if isinstance(tree, dict):
        for k, v in tree.items():
            if "/" in str(k):
                raise ValueError(f"parameter names may not contain '/': {k!r}")
            out.update(_flatten(v, f"{prefix}/{k}"))
    else:
        out[prefix] = np.asarray(tree)
    return out


def _unflatten(flat: dict[str, np.ndarray]) -> dict:
    root: dict = {}
    for key, v in flat.items():
        parts = key.split("/")
        d = root
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = jnp.asarray(v)
    return root


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode())
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_checkpoint(path: str, params: dict, *, db: TextDB | None = None, meta: dict | None = None) -> None:
    """Write ``params`` ({net name: pytree of dicts}) and optionally D_T to ``path`` (.npz),
    atomically (temporary file in the same directory, fsync, ``os.replace``)."""
    arrays: dict[str, np.ndarray] = {}
    for name, tree in params.items():
        arrays.update(_flatten(tree, f"p/{name}"))
    if db is not None:
        arrays["db/embeddings"] = np.asarray(db.embeddings, np.float32)
        arrays["db/captions"] = np.asarray(db.captions, dtype=np.str_)
        arrays["db/actions"] = np.asarray(db.actions, np.int32)
        if db.keys is not None:
            arrays["db/keys"] = np.asarray(db.keys, np.float32)
    header = {"format": FORMAT, "version": VERSION, "digest": _digest(arrays), "meta": meta or {}}
    buf = io.BytesIO()
    np.savez(buf, __meta__=np.asarray(json.dumps(header)), **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path: str) -> tuple[dict, TextDB | None, dict]:
    """(params, D_T or None, meta) from a checkpoint written by :func:`save_checkpoint`.
    Raises :class:`CheckpointError` for a missing, truncated, foreign or tampered file."""
    if not os.path.exists(path):
        raise CheckpointError(f"no checkpoint at {path!r}")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as e:
        raise CheckpointError(f"corrupt checkpoint {path!r}: {type(e).__name__}: {e}") from e
    if "__meta__" not in arrays:
        raise CheckpointError(f"{path!r} is not an OLiVia-Nav checkpoint (no header)")
    try:
        header = json.loads(str(arrays.pop("__meta__")))
    except ValueError as e:
        raise CheckpointError(f"corrupt checkpoint header in {path!r}") from e
    if header.get("format") != FORMAT or header.get("version") != VERSION:
        raise CheckpointError(f"{path!r} has format {header.get('format')!r} v{header.get('version')}, "
                              f"expected {FORMAT!r} v{VERSION}")
    if _digest(arrays) != header.get("digest"):
        raise CheckpointError(f"checkpoint {path!r} failed its integrity check (digest mismatch)")
    params = _unflatten({k[2:]: v for k, v in arrays.items() if k.startswith("p/")})
    db = None
    if "db/embeddings" in arrays:
        db = TextDB(arrays["db/embeddings"].astype(np.float32), [str(s) for s in arrays["db/captions"]],
                    arrays["db/actions"].astype(np.int32),
                    arrays["db/keys"].astype(np.float32) if "db/keys" in arrays else None)
    return params, db, header.get("meta", {})


def load_planner(path: str, variant: str = "olivia") -> OliviaNav:
    """An :class:`OliviaNav` from a full checkpoint (``clip``, ``tpn``, ``tsm`` and D_T)."""
    params, db, meta = load_checkpoint(path)
    if db is None or any(k not in params for k in ("clip", "tpn", "tsm")):
        raise CheckpointError(f"{path!r} is not a full OLiVia-Nav checkpoint (needs clip, tpn, tsm and D_T)")
    return OliviaNav(params, db, config_from_meta(meta), variant)


def config_to_meta(cfg: OliviaConfig) -> dict:
    return {"clip": dataclasses.asdict(cfg.clip), "tpn": dataclasses.asdict(cfg.tpn), "tsm": dataclasses.asdict(cfg.tsm),
            "replan_every": cfg.replan_every, "retrieve_k": cfg.retrieve_k, "retrieve_tau": cfg.retrieve_tau,
            "vote_memory": cfg.vote_memory, "score_weight": cfg.score_weight, "consistency": cfg.consistency,
            "safety": cfg.safety, "safety_margin": cfg.safety_margin, "text_gate": cfg.text_gate, "view_gate": cfg.view_gate, "pass_right": cfg.pass_right,
            "arrive_radius": cfg.arrive_radius, "oncoming_yield": cfg.oncoming_yield, "cross_tau": cfg.cross_tau,
            "people_react": cfg.people_react, "oncoming_time": cfg.oncoming_time, "route_fallback": cfg.route_fallback, "route_berth": cfg.route_berth,
            "perceived_berth": cfg.perceived_berth, "person_key": cfg.person_key, "person_weight": cfg.person_weight,
            "person_gate": cfg.person_gate, "person_view_gate": cfg.person_view_gate}


def config_from_meta(meta: dict) -> OliviaConfig:
    c = meta.get("config")
    if not c:
        return OliviaConfig()
    t = dict(c["tpn"])
    t["channels"] = tuple(t["channels"])
    t.setdefault("score", False)  # checkpoints from before the mode-score head
    return OliviaConfig(sc_clip.SCCLIPConfig(**c["clip"]), tpn.TPNConfig(**t), tsm.TSMConfig(**c["tsm"]),
                        replan_every=int(c.get("replan_every", 2)), retrieve_k=int(c.get("retrieve_k", 1)),
                        retrieve_tau=float(c.get("retrieve_tau", 0.05)), vote_memory=float(c.get("vote_memory", 0.0)),
                        score_weight=float(c.get("score_weight", 1.0 if t["score"] else 0.0)),
                        **{k: float(c[k]) for k in ("consistency", "safety", "safety_margin", "text_gate", "view_gate", "pass_right", "arrive_radius",
                                                    "cross_tau", "people_react", "oncoming_time", "route_berth",
                                                    "perceived_berth", "person_weight", "person_gate", "person_view_gate")
                           if k in c},
                        **{k: bool(c[k]) for k in ("oncoming_yield", "route_fallback", "person_key") if k in c})


# -- training loop --------------------------------------------------------------------------------

@dataclass
class StageResult:
    """params: the best epoch's; train, val: per-epoch mean losses; best_epoch; seconds; stopped_early."""

    params: Any
    train: list
    val: list
    best_epoch: int
    seconds: float
    stopped_early: bool


def fit(loss_fn: Callable, params, train_batches: Callable[[np.random.Generator], Sequence[dict]],
        val_batches: Sequence[dict], *, lr: float, weight_decay: float, epochs: int, patience: int,
        seed: int = 0, schedule: str = "constant", on_epoch: Callable | None = None,
        on_improve: Callable | None = None, min_delta: float = 1e-4) -> StageResult:
    """Minimise ``loss_fn(params, batch, key)`` with AdamW; after each epoch evaluate the mean
    validation loss (deterministic key), keep the best params, stop after ``patience`` epochs
    without an improvement of ``min_delta``. ``schedule``: "constant" or "cosine" (annealed over
    all planned steps). ``on_epoch(epoch, train, val)``, ``on_improve(params, epoch)``."""
    if epochs < 1 or patience < 1:
        raise ValueError("epochs and patience must be >= 1")
    rng = np.random.default_rng(seed)
    n_steps = epochs * max(len(train_batches(np.random.default_rng(seed))), 1)
    sched = optax.cosine_decay_schedule(lr, n_steps) if schedule == "cosine" else lr
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(sched, weight_decay=weight_decay))
    state = opt.init(params)

    @jax.jit
    def step(p, s, batch, key):
        lv, g = jax.value_and_grad(loss_fn)(p, batch, key)
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s, lv

    val_loss = jax.jit(loss_fn)
    key = jax.random.PRNGKey(seed)
    best, best_p, best_epoch, bad = np.inf, params, -1, 0
    tr_hist, va_hist = [], []
    t0 = time.perf_counter()
    stopped = False
    for ep in range(epochs):
        ls = []
        for batch in train_batches(rng):
            key, k = jax.random.split(key)
            params, state, lv = step(params, state, batch, k)
            ls.append(float(lv))
        vk = jax.random.PRNGKey(12345)
        v = float(np.mean([float(val_loss(params, b, vk)) for b in val_batches])) if val_batches else float(np.mean(ls))
        tr_hist.append(float(np.mean(ls)))
        va_hist.append(v)
        if on_epoch is not None:
            on_epoch(ep, tr_hist[-1], v)
        if v < best - min_delta:
            best, best_p, best_epoch, bad = v, params, ep, 0
            if on_improve is not None:
                on_improve(best_p, ep)
        else:
            bad += 1
            if bad >= patience:
                stopped = True
                break
    return StageResult(best_p, tr_hist, va_hist, best_epoch, time.perf_counter() - t0, stopped)


def batches(arrays: dict, batch: int, rng: np.random.Generator | None, drop_last: bool = True) -> list[dict]:
    """Mini-batches (dicts of jnp arrays) over the rows of ``arrays`` (shuffled with ``rng``)."""
    n = len(next(iter(arrays.values())))
    idx = rng.permutation(n) if rng is not None else np.arange(n)
    stop = n - batch + 1 if (drop_last and n >= batch) else n
    out = []
    for s in range(0, max(stop, 1), batch):
        sel = idx[s:s + batch]
        if len(sel) == 0:
            break
        out.append({k: jnp.asarray(v[sel]) for k, v in arrays.items()})
    return out


def val_batches(arrays: dict, max_rows: int) -> list[dict]:
    """Validation batches of one shape (one compilation of the validation loss): all rows in
    one batch when there are at most ``max_rows``, else equal chunks, the last one completed
    with rows from the start (a negligible bias of a few repeated rows)."""
    n = len(next(iter(arrays.values())))
    c = max(-(-n // max_rows), 1)
    size = -(-n // c)
    idx = np.arange(c * size) % max(n, 1)
    return [{k: jnp.asarray(np.asarray(v)[idx[i * size:(i + 1) * size]]) for k, v in arrays.items()} for i in range(c)]


# -- the pipeline ---------------------------------------------------------------------------------

def assert_held_out(s: Samples, scenario: str, seeds: Sequence[int]) -> None:
    """Raise ValueError when any sample of ``s`` comes from ``scenario`` with one of ``seeds``
    (the held-out doorway's adaptation and test seeds must never be trained on)."""
    from ..convoi.scenario_names import SCENARIOS

    bad = (np.asarray(s.scenario) == SCENARIOS.index(scenario)) & np.isin(np.asarray(s.seed), np.asarray(seeds))
    if bad.any():
        raise ValueError(f"{int(bad.sum())} training samples come from held-out {scenario} seeds "
                         f"{sorted(set(np.asarray(s.seed)[bad].tolist()))}")


@dataclass
class TrainConfig:
    """Data: scenarios, train / validation seeds, sampling stride (steps) and augmented copies.
    Per stage: epochs, batch, lr, weight decay; patience for early stopping; db_size: |D_T|."""

    scenarios: tuple = THESIS_SCENARIOS
    train_seeds: tuple = tuple(range(6))
    val_seeds: tuple = (50,)
    every: int = 5
    augment: int = 1
    clip_epochs: int = 16
    clip_batch: int = 128
    clip_lr: float = 1e-3
    clip_wd: float = 0.01
    tpn_epochs: int = 15
    tpn_batch: int = 32
    tpn_lr: float = 8e-4
    tpn_wd: float = 1e-4
    tsm_epochs: int = 40
    tsm_batch: int = 128
    tsm_lr: float = 1e-3
    tsm_wd: float = 1e-5
    tsm_counterfactual: bool = True
    patience: int = 5
    db_size: int = 1000
    seed: int = 0
    door_seeds: tuple = DOOR_TRAIN_SEEDS
    headon_door_seeds: tuple = HEADON_DOOR_SEEDS
    vary_geometry: bool = True
    # m: the goal features of the data follow the route around the standing people perceived so
    # far, the route the planner reads (OliviaConfig.perceived_berth); 0: the walls-only path
    perceived_berth: float = 0.8


def _text_arrays(s: Samples):
    li, lm = DEFAULT_TOKENIZER.encode_batch(s.long, LONG_LEN)
    si, sm = DEFAULT_TOKENIZER.encode_batch(s.short, SHORT_LEN)
    return {"image": s.image, "long_ids": li, "long_mask": lm, "short_ids": si, "short_mask": sm}


def map_rows(f: Callable, arrays: Sequence[np.ndarray], batch: int) -> np.ndarray:
    """``f(*chunks)`` over ``batch`` rows at a time, concatenated (host array). ``f`` must treat
    rows independently: the last chunk is padded to ``batch`` rows (and the padding dropped), so
    that a jitted ``f`` compiles for one shape only."""
    n = len(arrays[0])
    out = []
    for s in range(0, n, batch):
        chunk = [a[s:s + batch] for a in arrays]
        m = len(chunk[0])
        if m < batch:
            chunk = [np.concatenate([c, np.repeat(c[:1], batch - m, 0)]) for c in chunk]
        out.append(np.asarray(f(*map(jnp.asarray, chunk)))[:m])
    return np.concatenate(out)


# module level, so that every call with the same config and shapes reuses one compilation
_encode_images = jax.jit(sc_clip.encode_images, static_argnames="cfg")
_encode_texts = jax.jit(sc_clip.encode_texts, static_argnames="cfg")
_predict = jax.jit(lambda p, e, pt, v, g, cfg: tpn.predict(p, e, pt, v, g, True, True, cfg), static_argnames="cfg")


def encode_all_images(params, images: np.ndarray, cfg: sc_clip.SCCLIPConfig, batch: int = 256) -> np.ndarray:
    """(N, D) unit E_I of images (N, H, W, 3)."""
    return map_rows(lambda x: _encode_images(params, x, cfg=cfg), [images], batch).astype(np.float32)


def encode_all_texts(params, texts: list, cfg: sc_clip.SCCLIPConfig, batch: int = 256) -> np.ndarray:
    """(N, D) unit E_T of long captions."""
    ids, mask = DEFAULT_TOKENIZER.encode_batch(texts, LONG_LEN)
    return map_rows(lambda i, m: _encode_texts(params, i, m, cfg=cfg), [ids, mask], batch).astype(np.float32)


def predict_all(tpn_params, e_img, s: Samples, cfg: tpn.TPNConfig, batch: int = 128) -> np.ndarray:
    """τ^P (N, K, horizon, 3) of every sample, all modalities on."""
    return map_rows(lambda e, pt, v, g: _predict(tpn_params, e, pt, v, g, cfg=cfg),
                    [e_img, s.points, s.points_valid, s.goal], batch)


def k_stars(trajs: np.ndarray, s: Samples) -> np.ndarray:
    """(N,) k* of each sample: the plan performing its caption's action closest to its expert future."""
    return np.asarray([tsm.best_index(trajs[i], s.future[i], int(s.action[i])) for i in range(len(s))], np.int32)


def tsm_rows(trajs: np.ndarray, s: Samples, counterfactual: bool = True) -> tuple[list, np.ndarray, np.ndarray,
                                                                                  np.ndarray]:
    """D_TSM (eq 7) from the TPN's plans ``trajs`` (N, K, horizon, 3) of the samples ``s``.

    Each sample gives its own long caption with its k*. With ``counterfactual``, each other action
    that one of its K plans performs gives one more row: the caption rewritten to that action
    (:func:`~splatsearch.social.olivia.captions.with_action`) and k* the plan that performs it closest
    to the expert. Without them the expert's action is nearly always that of the plan closest to
    the expert, which the plans alone reveal, and the TSM learns to ignore E_T.

    Returns (captions, sample index of each row, k*, factual) with one entry per row."""
    caps, idx, ks, fact = [], [], [], []
    for i in range(len(s)):
        caps.append(s.long[i])
        idx.append(i)
        ks.append(tsm.best_index(trajs[i], s.future[i], int(s.action[i])))
        fact.append(True)
        if not counterfactual:
            continue
        for a in sorted({action_of(t) for t in trajs[i]} - {int(s.action[i])}):
            cap = with_action(s.long[i], a)
            if cap is None:
                continue
            caps.append(cap)
            idx.append(i)
            ks.append(tsm.best_index(trajs[i], s.future[i], a))
            fact.append(False)
    return caps, np.asarray(idx, np.int64), np.asarray(ks, np.int32), np.asarray(fact, bool)


def train_olivia(out_dir: str, tc: TrainConfig = TrainConfig(), cfg: OliviaConfig = OliviaConfig(),
                 log: Callable[[str], None] | None = None, progress=None) -> dict:
    """Run the three stages and write ``out_dir/olivia.npz`` (all networks + D_T), the stage
    checkpoints and ``out_dir/train_summary.json``. ``progress``: an optional
    ``rich.progress.Progress`` (a task per stage). Returns the summary dict."""
    log = log or logger.info  # a caller may pass console.log; the library logs by default
    os.makedirs(out_dir, exist_ok=True)
    t_start = time.perf_counter()
    summary: dict = {"config": config_to_meta(cfg), "train": dataclasses.asdict(tc)}
    meta = {"config": config_to_meta(cfg)}

    def task(name, total):
        return progress.add_task(name, total=total) if progress is not None else None

    def advance(tid, **kw):
        if progress is not None and tid is not None:
            progress.update(tid, **kw)

    # data --------------------------------------------------------------------------------------
    data_path = os.path.join(out_dir, "samples_train.npz")
    val_path = os.path.join(out_dir, "samples_val.npz")
    t0 = time.perf_counter()
    if os.path.exists(data_path) and os.path.exists(val_path):
        train, val = Samples.load(data_path), Samples.load(val_path)
        log(f"data: reused {len(train)} train / {len(val)} val samples from {out_dir}")
    else:
        n_jobs = len(tc.scenarios) * (len(tc.train_seeds) + len(tc.val_seeds)) + len(tc.door_seeds) + len(tc.headon_door_seeds)
        tid = task("expert episodes + renders", n_jobs)
        done = [0]

        def prog(i, n, label):
            done[0] += 1
            advance(tid, completed=done[0], description=f"expert {label}")

        kw = dict(every=tc.every, augment=tc.augment, progress=prog, vary_geometry=tc.vary_geometry,
                  perceived_berth=tc.perceived_berth)
        train = build_dataset(tc.scenarios, tc.train_seeds, **kw)
        if tc.door_seeds:
            # doors of sampled widths (1.02-1.6 m, the held-out doorway's 1.1 m inside), never its seeds
            train = Samples.concat([train, build_dataset(("doorway",), tc.door_seeds, **kw)])
        if tc.headon_door_seeds:
            # a person meeting the robot head-on just past the door: the walker steps aside and waits
            train = Samples.concat([train, build_dataset(("doorway",), tc.headon_door_seeds, headon=True, **kw)])
        val = build_dataset(tc.scenarios, tc.val_seeds, **kw)
        train.save(data_path)
        val.save(val_path)
    assert_held_out(train, "doorway", LLU_ADAPT_SEEDS + tuple(LLU_TEST_SEEDS))
    summary["data"] = {"train": len(train), "val": len(val), "seconds": time.perf_counter() - t0,
                       "actions": np.bincount(train.action, minlength=6).tolist()}
    log(f"data: {len(train)} train / {len(val)} val samples in {summary['data']['seconds']:.0f} s")

    key = jax.random.PRNGKey(tc.seed)
    k1, k2, k3 = jax.random.split(key, 3)

    # stage 1: SC-CLIP ---------------------------------------------------------------------------
    tr_a, va_a = _text_arrays(train), _text_arrays(val)
    tid = task("SC-CLIP (eq 3)", tc.clip_epochs)
    r1 = fit(lambda p, b, k: sc_clip.make_loss_fn(cfg.clip)(p, b), sc_clip.init_sc_clip(k1, cfg.clip),
             lambda rng: batches(tr_a, tc.clip_batch, rng), val_batches(va_a, 512),
             lr=tc.clip_lr, weight_decay=tc.clip_wd, epochs=tc.clip_epochs, patience=tc.patience, seed=tc.seed,
             schedule="cosine",
             on_epoch=lambda e, a, b: advance(tid, completed=e + 1, description=f"SC-CLIP train {a:.3f} val {b:.3f}"),
             on_improve=lambda p, e: save_checkpoint(os.path.join(out_dir, "sc_clip.npz"), {"clip": p}, meta=meta))
    clip_p = r1.params
    summary["sc_clip"] = _stage_summary(r1)
    log(f"SC-CLIP: val loss {min(r1.val):.3f} at epoch {r1.best_epoch + 1}/{len(r1.val)} ({r1.seconds:.0f} s)")

    # stage 2: TPN on frozen E_I ---------------------------------------------------------------
    e_tr = encode_all_images(clip_p, train.image, cfg.clip)
    e_va = encode_all_images(clip_p, val.image, cfg.clip)
    tp_tr = {"e_img": e_tr, "points": train.points, "points_valid": train.points_valid, "goal": train.goal,
             "future": train.future}
    tp_va = {"e_img": e_va, "points": val.points, "points_valid": val.points_valid, "goal": val.goal,
             "future": val.future}
    tid = task("TPN (eq 2, WTA)", tc.tpn_epochs)
    r2 = fit(tpn.make_loss_fn(cfg.tpn), tpn.init_tpn(k2, cfg.tpn), lambda rng: batches(tp_tr, tc.tpn_batch, rng),
             val_batches(tp_va, 512), lr=tc.tpn_lr, weight_decay=tc.tpn_wd, epochs=tc.tpn_epochs,
             patience=tc.patience, seed=tc.seed + 1, schedule="cosine",
             on_epoch=lambda e, a, b: advance(tid, completed=e + 1, description=f"TPN train {a:.4f} val {b:.4f}"),
             on_improve=lambda p, e: save_checkpoint(os.path.join(out_dir, "tpn.npz"), {"tpn": p}, meta=meta))
    tpn_p = r2.params
    summary["tpn"] = _stage_summary(r2)
    log(f"TPN: val WTA {min(r2.val):.4f} m² at epoch {r2.best_epoch + 1}/{len(r2.val)} ({r2.seconds:.0f} s)")

    # stage 3: TSM on the TPN's plans ------------------------------------------------------------
    traj_tr, traj_va = predict_all(tpn_p, e_tr, train, cfg.tpn), predict_all(tpn_p, e_va, val, cfg.tpn)

    def tsm_arrays(trajs, s):
        caps, idx, ks, fact = tsm_rows(trajs, s, tc.tsm_counterfactual)
        return {"e_text": encode_all_texts(clip_p, caps, cfg.clip), "trajs": trajs[idx], "k_star": ks,
                "factual": fact}

    ts_tr, ts_va = tsm_arrays(traj_tr, train), tsm_arrays(traj_va, val)
    tid = task("TSM (eq 7)", tc.tsm_epochs)
    r3 = fit(tsm.make_loss_fn(cfg.tsm), tsm.init_tsm(k3, cfg.tsm), lambda rng: batches(ts_tr, tc.tsm_batch, rng),
             val_batches(ts_va, 1024), lr=tc.tsm_lr, weight_decay=tc.tsm_wd, epochs=tc.tsm_epochs,
             patience=tc.patience, seed=tc.seed + 2,
             on_epoch=lambda e, a, b: advance(tid, completed=e + 1, description=f"TSM train {a:.3f} val {b:.3f}"),
             on_improve=lambda p, e: save_checkpoint(os.path.join(out_dir, "tsm.npz"), {"tsm": p}, meta=meta))
    tsm_p = r3.params

    # D_T: a random subset of the training long captions ----------------------------------------
    rng = np.random.default_rng(tc.seed)
    caps = list(dict.fromkeys(train.long))
    caps = [caps[i] for i in rng.permutation(len(caps))[: tc.db_size]]
    db = build_text_db(clip_p, caps, cfg.clip)
    params = {"clip": clip_p, "tpn": tpn_p, "tsm": tsm_p}
    save_checkpoint(os.path.join(out_dir, "olivia.npz"), params, db=db, meta=meta)
    summary["tsm"] = _stage_summary(r3) | tsm_diagnostics(tsm_p, ts_va, e_va, val.action, db, cfg)
    d = summary["tsm"]
    log(f"TSM: val CE {min(r3.val):.3f}; selection accuracy {d['acc_caption']:.2f} with the true caption, "
        f"{d['acc_retrieved']:.2f} with the retrieved one, {d['acc_no_text']:.2f} without E_T, "
        f"{d['acc_counterfactual']:.2f} on rewritten captions; retrieved action right {d['retrieval_action']:.2f} "
        f"({r3.seconds:.0f} s)")
    summary["db_size"] = len(db.captions)
    summary["seconds"] = time.perf_counter() - t_start
    atomic_write_bytes(os.path.join(out_dir, "train_summary.json"), json.dumps(summary, indent=1).encode())
    log(f"wrote {os.path.join(out_dir, 'olivia.npz')} (total {summary['seconds']:.0f} s)")
    return summary


def tsm_diagnostics(tsm_p, rows: dict, e_img: np.ndarray, actions: np.ndarray, db: TextDB,
                    cfg: OliviaConfig) -> dict:
    """How the TSM selects on validation rows (from :func:`tsm_rows`; the factual ones come
    first per sample, in sample order): accuracy against k* with the sample's own caption, with
    the caption D_T retrieves for its image (what the planner gets, :func:`retrieve`), without
    E_T, and on the rewritten captions; and how often the retrieved caption's action is the
    sample's."""
    fact = np.asarray(rows["factual"])
    trajs, ks = np.asarray(rows["trajs"]), np.asarray(rows["k_star"])
    f = jax.jit(lambda e, t, u: tsm.TSM(cfg.tsm).apply({"params": tsm_p}, e, t, u))

    def acc(e_text, tr, k, use):
        if not len(k):
            return float("nan")
        sel = map_rows(lambda e, t: jnp.argmax(f(e, t, jnp.full(len(t), use)), -1), [e_text, tr], 512)
        return float(np.mean(sel == k))

    ret = jax.jit(jax.vmap(lambda e: retrieve(jnp.asarray(db.embeddings), jnp.asarray(db.actions, jnp.int32), e,
                                              cfg.retrieve_k, cfg.retrieve_tau)[0]))
    j = np.asarray(ret(jnp.asarray(e_img, jnp.float32)))
    e_ret = db.embeddings[j]
    return {"acc_caption": acc(rows["e_text"][fact], trajs[fact], ks[fact], True),
            "acc_retrieved": acc(e_ret, trajs[fact], ks[fact], True),
            "acc_no_text": acc(rows["e_text"][fact], trajs[fact], ks[fact], False),
            "acc_counterfactual": acc(rows["e_text"][~fact], trajs[~fact], ks[~fact], True),
            "retrieval_action": float(np.mean(np.asarray(db.actions)[j] == np.asarray(actions)))}


def _stage_summary(r: StageResult) -> dict:
    return {"train": r.train, "val": r.val, "best_epoch": r.best_epoch, "seconds": r.seconds,
            "stopped_early": r.stopped_early}


# -- evaluation -----------------------------------------------------------------------------------

def episode_metrics(res, ref) -> dict:
    """MSE (m²) and Hausdorff (m) against the reference path ``ref`` (EpisodeResult), PSV (s, edge
    gap < 0.25 m), goal reached, plan ms, and the SEANavBench-style metrics of
    :func:`~splatsearch.social.convoi.metrics.social_metrics` (completion, path irregularity,
    time not moving, personal / intimate zone time, min distance to people)."""
    from ..convoi.metrics import hausdorff, mse, psv_duration, social_metrics

    return {"mse": mse(res.robot, ref.robot), "haus": hausdorff(res.robot, ref.robot),
            "psv": psv_duration(res.robot[:, :2], res.people, res.dt, 0.25, valid=res.active, robot_radius=0.25,
                                person_radius=0.25),
            "reached": bool(res.reached), "plan_ms": float(res.plan_ms)} | social_metrics(
                res.robot, res.people, res.active, res.dt, res.reached)


def win_counts(per: dict[str, list], ours: str = "OLiVia-Nav") -> dict[str, dict]:
    """Per-seed wins of ``ours`` over every other method of ``per`` ({method: [episode
    metrics per seed, same seed order]}): {method: {"mse": n, "haus": n, "psv": n (strictly
    lower), "psv_ties": n, "n": seeds}}."""
    out = {}
    if ours not in per:
        return out
    mine = per[ours]
    for method, ms in per.items():
        if method == ours:
            continue
        out[method] = {k: int(sum(a[k] < b[k] for a, b in zip(mine, ms))) for k in ("mse", "haus", "psv")}
        out[method]["psv_ties"] = int(sum(a["psv"] == b["psv"] for a, b in zip(mine, ms)))
        out[method]["n"] = len(ms)
    return out


def _mean(rows: list[dict]) -> dict:
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if not isinstance(rows[0][k], dict)} if rows else {}


def run_baseline(scn, kind: str, cache: "BaselineCache | None" = None):
    """The episode of the non-learned planner ``kind`` ("dwa", "convoi", "human", "expert") on
    ``scn``; read from / stored in ``cache`` when one is given."""
    from ..convoi.runner import run_episode

    def run():
        if kind == "convoi":
            from ..convoi.pipeline import CoNVOI
            from ..convoi.vlm import RuleBasedVLM

            return run_episode(scn, "convoi", convoi=CoNVOI(RuleBasedVLM()))
        return run_episode(scn, kind)

    return run() if cache is None else cache.get(scn, kind, run)


def table_one(planner: OliviaNav, scenarios: Sequence[str] = THESIS_SCENARIOS, seeds: Sequence[int] = TABLE_ONE_SEEDS,
              baselines: Sequence[str] = ("dwa", "convoi"), variants: Sequence[str] = ("olivia",),
              log: Callable[[str], None] | None = None, progress=None,
              cache: "BaselineCache | None" = None) -> list[dict]:
    """Table I form: per scenario and method, metrics averaged over the held-out ``seeds``
    (reference and baseline episodes through ``cache`` when given)."""
    log = log or logger.info  # a caller may pass console.log; the library logs by default
    rows = []
    names = {"dwa": "DWA", "convoi": "CoNVOI+DWA"}
    tid = progress.add_task("Table I", total=len(scenarios) * len(seeds)) if progress is not None else None
    for name in scenarios:
        per: dict[str, list] = {}
        for seed in seeds:
            scn = make_scenario(name, seed)
            ref = run_baseline(scn, REFERENCE, cache)
            for v in variants:
                per.setdefault(VARIANT_LABELS[v], []).append(episode_metrics(run_olivia_episode(scn, planner.with_variant(v)), ref))
            for b in baselines:
                per.setdefault(names.get(b, b), []).append(episode_metrics(run_baseline(scn, b, cache), ref))
            if progress is not None:
                progress.advance(tid)
        wins = win_counts(per)
        for method, ms in per.items():
            rows.append({"scenario": name, "method": method, "n": len(ms)} | _mean(ms)
                        | ({"wins": wins[method]} if method in wins else {}))
        log(f"Table I: {name} done")
    return rows


def reference_shift_of(scn, cache: "BaselineCache | None" = None) -> Callable[[int], float]:
    """Step -> the lateral shift (m) the reference walker holds at that step of its own episode
    on ``scn`` (:attr:`EpisodeResult.shifts`, the last one past its end). The episode is run (or
    read from ``cache``) on the first call only: a lazy buffer captions a few views per seed.
    With the DWA-with-critics reference (no shift) it is always 0."""
    from ..convoi.runner import REFERENCE, WALKERS

    held: list = []

    def shift(t: int) -> float:
        if REFERENCE not in WALKERS:
            return 0.0
        if not held:
            held.append(run_baseline(scn, REFERENCE, cache).shifts)
        s = held[0]
        return 0.0 if s is None or len(s) == 0 else float(s[min(int(t), len(s) - 1)])

    return shift


def fill_buffer(planner: OliviaNav, scenario: str, adapt_seeds: Sequence[int], size: int,
                buffer_every: int = 2, oncoming_share: float = 0.0, cache: "BaselineCache | None" = None,
                carry_shift: bool = True, caption_keep: float | None = None) -> tuple[LLUBuffer, list[int]]:
    """The LLU buffer B of |B| = ``size`` images from OLiVia-Nav driving the adaptation episodes
    of ``scenario`` (every ``buffer_every``-th plan offers its view). Returns B and the seeds
    driven. Raises RuntimeError when the episodes end before B is full: the update is defined on
    a full buffer.

    ``oncoming_share`` 0: the seeds are driven in order until B is full (the first views).
    Above 0: every seed is driven, and B keeps up to ``oncoming_share`` x |B| of the views
    where the robot saw someone walking head-on toward it (:func:`planner.oncoming_count`),
    the rest spread evenly over the other views of all episodes. The first views of a few
    doorway episodes show a person coming diagonally through the door, and head-on meetings
    (where the reference steps aside) are rarer; a buffer without them cannot teach them.
    Only the kept views are captioned.

    ``carry_shift``: the captioner's walker is forked with the lateral shift the reference's own
    episode holds at that step (:func:`reference_shift_of`, episodes through ``cache``); False:
    with none (before stop 45: it undid the reference's head-on sidestep at 2-3 s).
    ``caption_keep`` (m): the side threshold of the captions' action
    (:attr:`LLUConfig.caption_keep`); None: the training data's 0.35 m."""
    keep = {} if caption_keep is None else {"caption_keep": float(caption_keep)}
    if not 0.0 <= oncoming_share <= 1.0:
        raise ValueError(f"oncoming_share must be in [0, 1], got {oncoming_share}")
    used: list[int] = []
    if oncoming_share == 0.0:
        buf = LLUBuffer(size)
        for seed in adapt_seeds:
            if buf.full:
                break
            scn = make_scenario(scenario, seed)
            run_olivia_episode(scn, planner, buffer=buf, buffer_every=buffer_every,
                               reference_shift=reference_shift_of(scn, cache) if carry_shift else None, **keep)
            used.append(int(seed))
    else:
        pool = LLUBuffer(10 ** 9, lazy=True)
        for seed in adapt_seeds:
            scn = make_scenario(scenario, seed)
            run_olivia_episode(scn, planner, buffer=pool, buffer_every=buffer_every,
                               reference_shift=reference_shift_of(scn, cache) if carry_shift else None, **keep)
            used.append(int(seed))
        if len(pool.images) >= size:
            buf = pool.select(select_views(np.asarray(pool.oncoming), size, oncoming_share), size)
        else:
            buf = pool.select(range(len(pool.images)), size)
    if not buf.full:
        raise RuntimeError(f"the LLU buffer holds {len(buf.images)} of |B| = {size} images after the adaptation "
                           f"episodes {tuple(adapt_seeds)}: give more adaptation seeds or a smaller buffer_every")
    return buf, used


def select_views(oncoming: np.ndarray, size: int, share: float) -> list[int]:
    """Indices (sorted) of ``size`` views out of ``len(oncoming)``: up to ``round(share * size)``
    of those with ``oncoming`` > 0, evenly spaced among them, and the rest evenly spaced among
    the others (or more oncoming ones when the others run short)."""
    n = len(oncoming)
    if size > n:
        raise ValueError(f"cannot keep {size} of {n} views")
    on = np.flatnonzero(oncoming > 0)
    off = np.flatnonzero(oncoming <= 0)
    k_on = min(len(on), int(round(share * size)))
    k_on = max(k_on, size - len(off))
    spread = lambda idx, k: idx[np.unique(np.linspace(0, len(idx) - 1, k).round().astype(int))] if k else idx[:0]  # noqa: E731
    pick = np.concatenate([spread(on, k_on), spread(off, size - k_on)])
    return sorted(int(i) for i in pick)


def llu_effect(before: OliviaNav, after: OliviaNav, buf: LLUBuffer, captions: Sequence[str]) -> dict:
    """What one LLU update changed on the buffer's own views (eq 4's mechanism, step by step):
    the actions of the new captions; for each view, the action of the caption D_T retrieves
    (before / after), the TSM's selected plan index and that plan's action (before / after);
    and how often the selected plan now performs the caption's action."""
    from .captions import ACTIONS, action_from_text

    cap_act = [action_from_text(c) for c in captions]
    rows = []
    persons = buf.persons if len(buf.persons) == len(buf.observations) else [None] * len(buf.observations)
    for obs, a, ps in zip(buf.observations, cap_act, persons):
        if obs is None:
            continue
        pb = before.plan(obs.image, obs.points, obs.points_valid, obs.goal, person=ps)
        pa = after.plan(obs.image, obs.points, obs.points_valid, obs.goal, person=ps)
        rows.append({"caption_action": int(a), "retrieved_before": pb.action, "retrieved_after": pa.action,
                     "index_before": pb.index, "index_after": pa.index,
                     "plan_action_before": action_of(pb.trajs[pb.index]),
                     "plan_action_after": action_of(pa.trajs[pa.index])})
    n = max(len(rows), 1)
    frac = lambda k, ref="caption_action": sum(r[k] == r[ref] for r in rows) / n  # noqa: E731
    return {"caption_actions": {ACTIONS[i]: int(sum(c == i for c in cap_act)) for i in range(len(ACTIONS))},
            "views": len(rows),
            "retrieved_action_right_before": frac("retrieved_before"),
            "retrieved_action_right_after": frac("retrieved_after"),
            "selected_index_changed": sum(r["index_before"] != r["index_after"] for r in rows) / n,
            "plan_action_right_before": frac("plan_action_before"),
            "plan_action_right_after": frac("plan_action_after"),
            "per_view": rows}


def caption_buffer(buf: LLUBuffer) -> list[str]:
    """The long captions of the buffer's views by the template captioner (the offline stand-in
    for the large VLM; it reads each view's privileged scene)."""
    cap = TemplateCaptioner()
    return [cap.caption(im, sc, variant=i).long for i, (im, sc) in enumerate(zip(buf.images, buf.scenes))]


def apply_llu(planner: OliviaNav, buf: LLUBuffer, captions: Sequence[str], llu: LLUConfig = LLUConfig(),
              train_captions: Sequence[str] | None = None) -> tuple[OliviaNav, list[float]]:
    """One LLU update (i -> i+1) of ``planner`` on the buffer's images and their ``captions``:
    eq 4 fine-tunes F_I and F_T (:func:`llu_update`), D_T is rebuilt with the new F_T from the
    offline captions (``train_captions``, default the planner's D_T's) plus the new ones, and with
    ``llu.view_entries`` gets one entry per view keyed by its E_I (:func:`add_view_entries`).
    Returns the updated planner (whose TPN keeps the F_I it was trained with, ``clip_tpn``, unless
    ``llu.tpn_encoder`` is "updated") and eq 4's per-step losses."""
    imgs = np.stack([(np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8) if im.dtype != np.uint8 else im
                     for im in buf.images])
    new_clip, losses = llu_update(planner.params["clip"], imgs, list(captions), llu, planner.cfg.clip)
    base = list(train_captions) if train_captions is not None else list(planner.db.captions)
    db = build_text_db(new_clip, base + list(captions), planner.cfg.clip)
    if llu.view_entries:
        db = add_view_entries(db, encode_all_images(new_clip, imgs, planner.cfg.clip),
                              encode_all_texts(new_clip, list(captions), planner.cfg.clip), list(captions),
                              np.stack(buf.persons) if len(buf.persons) == len(captions) else None)
    if llu.tpn_encoder == "updated":  # the thesis: F_I^(i_t) feeds the TPN and retrieval alike
        params = {k: v for k, v in planner.params.items() if k != "clip_tpn"} | {"clip": new_clip}
    else:  # the TPN keeps the E_I it was trained on: fine-tuning F_I moved it enough to break plans (stop 34)
        params = dict(planner.params, clip=new_clip, clip_tpn=planner.params.get("clip_tpn", planner.params["clip"]))
    after = OliviaNav(params, db, planner.cfg, planner.variant)
    return after, losses


def table_two(planner: OliviaNav, scenario: str = "doorway", adapt_seeds: Sequence[int] = LLU_ADAPT_SEEDS,
              test_seeds: Sequence[int] = LLU_TEST_SEEDS, llu: LLUConfig = LLUConfig(),
              train_captions: Sequence[str] | None = None, log: Callable[[str], None] | None = None,
              progress=None, buffer_every: int = 2, oncoming_share: float = 0.5,
              cache: BaselineCache | None = None, variants: Sequence[str] = VARIANTS,
              before_variants: Sequence[str] | None = None) -> tuple[list[dict], OliviaNav, dict]:
    """Table II form on a scenario held out of training: every variant before and after one LLU
    update (i_t = 1, |B| = ``llu.size``). The buffer fills while OLiVia-Nav drives the
    ``adapt_seeds`` episodes, as many as it takes (:func:`fill_buffer`); its images are captioned
    by the template captioner (the offline stand-in for the VLM); D_T is rebuilt from its
    offline captions plus the new ones. The info dict holds the update's mechanism
    (:func:`llu_effect`), D_T's size before and after, and per-seed before/after metrics.
    The reference episodes are run once per test seed (through ``cache`` when given).
    ``variants``: those evaluated after the update; ``before_variants`` (default: the same)
    before it (a variant not run before gets NaN and reached -1 there)."""
    log = log or logger.info  # a caller may pass console.log; the library logs by default
    if set(adapt_seeds) & set(test_seeds):
        raise ValueError(f"adaptation seeds {sorted(set(adapt_seeds) & set(test_seeds))} are also test seeds")
    refs: dict[int, Any] = {}

    def evaluate(p: OliviaNav, variants: Sequence[str]) -> dict:
        out = {}
        for seed in test_seeds:
            scn = make_scenario(scenario, seed)
            if seed not in refs:
                refs[seed] = run_baseline(scn, REFERENCE, cache)
            ref = refs[seed]
            for v in variants:
                out.setdefault(v, []).append(episode_metrics(run_olivia_episode(scn, p.with_variant(v)), ref))
            if progress is not None:
                progress.advance(tid)
        return out

    tid = progress.add_task("Table II", total=2 * len(test_seeds)) if progress is not None else None
    before_seeds = evaluate(planner, variants if before_variants is None else before_variants)
    buf, used = fill_buffer(planner, scenario, adapt_seeds, llu.size, buffer_every, oncoming_share, cache,
                            caption_keep=llu.caption_keep)
    captions = caption_buffer(buf)
    after_planner, losses = apply_llu(planner, buf, captions, llu, train_captions)
    db = after_planner.db
    effect = llu_effect(planner, after_planner, buf, captions)
    log(f"LLU: |B| = {len(buf.images)}, eq 4 loss {losses[0]:.3f} -> {losses[-1]:.3f}; |D_T| {len(planner.db.captions)} "
        f"-> {len(db.captions)}; on the buffer's views the retrieved caption's action is right "
        f"{effect['retrieved_action_right_before']:.2f} -> {effect['retrieved_action_right_after']:.2f}, the selected "
        f"plan performs the caption's action {effect['plan_action_right_before']:.2f} -> "
        f"{effect['plan_action_right_after']:.2f}, selected index changed on {effect['selected_index_changed']:.2f}")
    after_seeds = evaluate(after_planner, variants)
    before = {v: _mean(r) for v, r in before_seeds.items()}
    after = {v: _mean(r) for v, r in after_seeds.items()}
    nan = {"mse": float("nan"), "haus": float("nan"), "psv": float("nan")}
    before = {v: before.get(v, nan) for v in variants}
    rows = [{"method": VARIANT_LABELS[v], "mse_before": before[v]["mse"], "haus_before": before[v]["haus"],
             "mse_after": after[v]["mse"], "haus_after": after[v]["haus"],
             "reached_before": int(sum(m["reached"] for m in before_seeds.get(v, []))) if v in before_seeds else -1,
             "reached_after": int(sum(m["reached"] for m in after_seeds[v])), "n": len(test_seeds),
             "psv_before": before[v]["psv"], "psv_after": after[v]["psv"],
             "min_dist_after": after[v]["min_dist"], "intimate_s_after": after[v]["intimate_s"]}
            for v in variants]
    info = {"llu_losses": losses, "buffer": len(buf.images), "adapt_seeds": used, "captions": captions,
            "buffer_oncoming": int(sum(o > 0 for o in buf.oncoming)), "buffer_episodes": list(buf.episodes),
            "db_before": len(planner.db.captions), "db_after": len(db.captions), "effect": effect,
            "per_seed": {"before": before_seeds, "after": after_seeds}}
    return rows, after_planner, info


def format_table_one(rows: list[dict]) -> str:
    """Table I in markdown: the thesis' MSE / Hausdorff / PSV, OLiVia-Nav's per-seed wins over
    each baseline (MSE / Haus / PSV strictly lower, of n), then the SEANavBench-style metrics."""
    lines = ["| Scenario | Method | MSE ↓ (m²) | Haus ↓ (m) | PSV ↓ (s) | OLiVia wins MSE/Haus/PSV | completed | "
             "irregularity (rad/m) | not moving (s) | personal (s) | intimate (s) | min dist (m) | plan ms |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w = r.get("wins")
        ws = f"{w['mse']}/{w['haus']}/{w['psv']} of {w['n']}" if w else ""
        lines.append(f"| {r['scenario']} | {r['method']} | {r['mse']:.4f} | {r['haus']:.4f} | {r['psv']:.1f} | {ws} | "
                     f"{r.get('completed', r['reached']):.2f} | {r.get('irregularity', float('nan')):.2f} | "
                     f"{r.get('not_moving_s', float('nan')):.1f} | {r.get('personal_s', float('nan')):.1f} | "
                     f"{r.get('intimate_s', float('nan')):.1f} | {r.get('min_dist', float('nan')):.2f} | "
                     f"{r['plan_ms']:.1f} |")
    return "\n".join(lines)


def format_table_two(rows: list[dict]) -> str:
    lines = ["| Method | MSE before ↓ | Haus before ↓ | reached before | MSE after ↓ | Haus after ↓ | reached after | "
             "MSE change |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ch = (r["mse_after"] - r["mse_before"]) / max(r["mse_before"], 1e-9)
        lines.append(f"| {r['method']} | {r['mse_before']:.4f} | {r['haus_before']:.4f} | "
                     f"{r.get('reached_before', '')}/{r.get('n', '')} | {r['mse_after']:.4f} | {r['haus_after']:.4f} | "
                     f"{r.get('reached_after', '')}/{r.get('n', '')} | {100 * ch:+.0f} % |")
    return "\n".join(lines)
