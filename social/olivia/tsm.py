"""OLiVia-Nav's Trajectory Selection Module (TSM, thesis 3.2.3, eq 7).

E_T (D,) goes through an FFN to E_τ; each of the K planned trajectories (horizon, 3) goes
through a per-pose FFN and a GRU to E_C; a final FFN scores ``E_C ⊕ E_τ`` per trajectory, and
eq 7 is the cross-entropy of those K scores against k*, the index of the trajectory that the
caption's navigation action describes (:func:`best_index`).

For the selection to depend on E_T, D_TSM also holds counterfactual rows (the same plans with the
caption rewritten to another action that one of them performs, and k* that plan; see
:func:`splatsearch.social.olivia.train.tsm_rows`): with the real captions alone, the expert's
action is nearly always that of the plan closest to the expert, which the plans reveal by
themselves, and a TSM trained on them scores the plans the same with or without E_T.
"""

from __future__ import annotations

from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from .features import HORIZON, action_of

F32 = jnp.float32


@dataclass(frozen=True)
class TSMConfig:
    """embed: D of E_T; width: E_τ and E_C size; K, horizon: the TPN's output shape."""

    embed: int = 64
    width: int = 64  # ample for ranking K plans by an action; 128 cost 4x the GRU time for nothing measurable
    K: int = 5
    horizon: int = HORIZON


class TSM(nn.Module):
    """e_text (B, D), trajs (B, K, horizon, 3), use_text (B,) bool -> logits (B, K).
    With ``use_text`` False, E_T is replaced by zeros (the w/o E_T ablation)."""

    cfg: TSMConfig

    @nn.compact
    def __call__(self, e_text, trajs, use_text):
        c = self.cfg
        B, K = trajs.shape[:2]
        # float32 throughout, also when the caller runs JAX with x64 on (the GRU's carry is float32)
        trajs = jnp.asarray(trajs, F32)
        e_text = jnp.where(use_text[:, None], jnp.asarray(e_text, F32), 0.0)
        e_tau = nn.Dense(c.width)(nn.relu(nn.Dense(c.width)(e_text)))  # FFN(E_T) = E_τ
        x = nn.relu(nn.Dense(64)(trajs.reshape(B * K, c.horizon, 3)))  # per-pose FFN
        e_c = nn.RNN(nn.GRUCell(c.width))(x)[:, -1].reshape(B, K, c.width)  # GRU -> E_C
        z = jnp.concatenate([e_c, jnp.broadcast_to(e_tau[:, None], (B, K, c.width))], -1)
        return nn.Dense(1)(nn.relu(nn.Dense(c.width)(z)))[..., 0]


def init_tsm(key, cfg: TSMConfig = TSMConfig()):
    return jax.jit(TSM(cfg).init)(key, jnp.zeros((1, cfg.embed), F32), jnp.zeros((1, cfg.K, cfg.horizon, 3), F32),
                         jnp.ones(1, bool))["params"]


def tsm_loss(logits, k_star):
    """eq 7: mean cross-entropy of logits (B, K) against k* (B,) int."""
    return -jnp.mean(jnp.take_along_axis(jax.nn.log_softmax(logits, -1), k_star[:, None].astype(jnp.int32), 1))


def make_loss_fn(cfg: TSMConfig = TSMConfig(), p_drop_text: float = 0.15):
    """``loss(params, batch, key)`` for batches ``{e_text, trajs, k_star}`` and optionally
    ``factual`` (B,) bool. E_T is dropped per sample with ``p_drop_text`` (so the w/o E_T ablation
    is a network that has seen it missing), but only from factual rows: a counterfactual row's
    k* follows its rewritten caption, so without E_T its target would be noise."""
    model = TSM(cfg)

    def loss(params, batch, key):
        B = batch["k_star"].shape[0]
        drop = jax.random.uniform(key, (B,)) < p_drop_text
        if "factual" in batch:
            drop = drop & batch["factual"]
        return tsm_loss(model.apply({"params": params}, batch["e_text"], batch["trajs"], ~drop), batch["k_star"])

    return loss


def best_index(trajs, expert, action: int) -> int:
    """k*: among the K trajectories (K, horizon, 3) whose :func:`action_of` equals ``action``,
    the closest to the expert's (horizon, 3) future (mean squared position error); if none
    performs the action, the closest overall."""
    trajs = np.asarray(trajs, np.float64)
    err = np.mean(np.sum((trajs[..., :2] - np.asarray(expert, np.float64)[None, :, :2]) ** 2, -1), -1)
    match = np.array([action_of(t) == action for t in trajs])
    if match.any():
        err = np.where(match, err, np.inf)
    return int(np.argmin(err))
