"""OLiVia-Nav's Trajectory Planning Network (TPN, thesis 3.2.2, eq 1, 2, 5, 6).

* SCEB: a LiDAR voxel encoder and a goal encoder.
  - LiDAR: points (N, 4) ``(x, y, z, age)`` in the robot frame are grouped into BEV pillars
    (``bev`` x ``bev`` cells of ``cell`` m, x from ``x_min``, y from ``y_min``); a voxel feature
    encoder (VoxelNet's VFE: a point-wise layer, then max-pooling over the points of each voxel,
    plus per-sweep point counts) gives a (bev, bev, F) grid; a stride-2 stem and five residual
    blocks (the second stage strided) give 8 x 8 tokens E_L of width C.
  - Goal: a single-layer FFN with ReLU -> E_G (1 token).
  - E_I (D,) from SC-CLIP is projected by an FFN to ``img_tokens`` tokens of width C.
* MHAB: a learned query Q^(0) (K tokens, one per head of the TFH) goes through three
  cross-attention layers in order (SC-CLIP, LiDAR, goal); each is eq 5 then eq 6:
  ``Q_att = LN(Q + A(Q, ·))``, ``Q' = LN(Q_att + FFN(Q_att))``. C = 128, 32 heads.
  Every key set also holds one learned *null* token, so a modality can be masked out entirely
  (the ablations w/o E_I, w/o E_L, and modality dropout in training) without an empty softmax.
* TFH: K GRUs (separate weights), each unrolled over the horizon from its query token and
  predicting pose increments, accumulated into 10 future poses ``(x, y, φ)`` (eq 1).
* eq 2: the winner-takes-all loss over the K heads (optionally relaxed: ``eps`` of the loss is
  spread over the losing heads so that none of them stays untrained).
* Mode scores (not in the thesis; ``score=True``): an FFN on each head's query token gives one logit
  per plan, trained by cross-entropy against the WTA winner (the head closest to the reference),
  as multi-modal motion predictors do (MultiPath, MTP). The TSM chooses among the plans from E_T
  and the plans alone; these scores carry what the LiDAR and goal say about which plan a person
  would take, and the planner adds them to the TSM's (see :mod:`splatsearch.social.olivia.planner`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from splatsearch.nav.grid import wrap_angle

from .features import GOAL_DIM, HORIZON
from .lidar import N_POINTS

F32 = jnp.float32


@dataclass(frozen=True)
class TPNConfig:
    """C: common width; heads: MHAB heads; K: trajectories (GRU heads); horizon: poses per
    trajectory; bev, cell, x_min, y_min: the pillar grid (cells, m); vfe: VFE width;
    channels: the five residual blocks' widths (the third one strides to half resolution);
    img_tokens: tokens made from E_I; embed: D of E_I; gru: GRU hidden size; step_scale:
    metres (and radians) per unit of the GRU's increment output."""

    C: int = 128
    heads: int = 32
    K: int = 5
    horizon: int = HORIZON
    bev: int = 32
    cell: float = 0.25
    x_min: float = -2.0
    y_min: float = -4.0
    vfe: int = 16
    channels: tuple = (16, 16, 32, 32, 32)
    img_tokens: int = 4
    embed: int = 64
    goal_dim: int = GOAL_DIM
    gru: int = 128
    step_scale: float = 0.3
    score: bool = True  # mode-score head (one logit per plan); False for checkpoints without one

    def __post_init__(self):
        if self.C % self.heads:
            raise ValueError(f"C={self.C} is not divisible by heads={self.heads}")
        if len(self.channels) != 5:
            raise ValueError("the LiDAR encoder has exactly five residual blocks")
        if self.K < 1 or self.horizon < 1 or self.bev % 4:
            raise ValueError("need K >= 1, horizon >= 1 and bev divisible by 4")


def pillar_index(points, valid, cfg: TPNConfig):
    """(N,) int32 pillar index ``row * bev + col`` of each point (row along y, col along x), or
    ``bev * bev`` (a dump slot) for invalid points and points outside the grid."""
    col = jnp.floor((points[:, 0] - cfg.x_min) / cfg.cell).astype(jnp.int32)
    row = jnp.floor((points[:, 1] - cfg.y_min) / cfg.cell).astype(jnp.int32)
    inside = valid & (col >= 0) & (col < cfg.bev) & (row >= 0) & (row < cfg.bev)
    return jnp.where(inside, row * cfg.bev + col, cfg.bev * cfg.bev)


class VFE(nn.Module):
    """Voxel feature encoder: points (N, 4), valid (N,) -> (bev, bev, vfe + 2) grid (max-pooled
    point features, and log point counts per sweep). Empty pillars read 0."""

    cfg: TPNConfig

    @nn.compact
    def __call__(self, points, valid):
        c = self.cfg
        idx = pillar_index(points, valid, c)
        n_seg = c.bev * c.bev + 1
        col = jnp.clip((points[:, 0] - c.x_min) / c.cell, 0, c.bev - 1e-3)
        row = jnp.clip((points[:, 1] - c.y_min) / c.cell, 0, c.bev - 1e-3)
        # point features: position, height, sweep age, offset from its pillar centre
        feat = jnp.stack([points[:, 0] / 4.0, points[:, 1] / 4.0, points[:, 2] - 1.0, points[:, 3],
                          col - jnp.floor(col) - 0.5, row - jnp.floor(row) - 0.5], -1)
        h = nn.relu(nn.Dense(c.vfe)(feat))
        pooled = jax.ops.segment_max(h, idx, n_seg)
        pooled = jnp.where(jnp.isfinite(pooled), pooled, 0.0)[:-1]
        cnt = jnp.stack([jax.ops.segment_sum((points[:, 3] == a).astype(F32), idx, n_seg)[:-1] for a in (0.0, 1.0)], -1)
        grid = jnp.concatenate([pooled, jnp.log1p(cnt)], -1)
        return grid.reshape(c.bev, c.bev, -1)


class ResBlock(nn.Module):
    """3x3 conv - ReLU - 3x3 conv, plus the input (1x1 projected when the shape changes), ReLU."""

    ch: int
    stride: int = 1

    @nn.compact
    def __call__(self, x):
        h = nn.relu(nn.Conv(self.ch, (3, 3), strides=self.stride)(x))
        h = nn.Conv(self.ch, (3, 3))(h)
        if self.stride != 1 or x.shape[-1] != self.ch:
            x = nn.Conv(self.ch, (1, 1), strides=self.stride)(x)
        return nn.relu(x + h)


class LidarEncoder(nn.Module):
    """points (B, N, 4), valid (B, N) -> E_L tokens (B, (bev/4)², C)."""

    cfg: TPNConfig

    @nn.compact
    def __call__(self, points, valid):
        c = self.cfg
        # one VFE (shared weights) mapped over the batch
        vfe = nn.vmap(VFE, variable_axes={"params": None}, split_rngs={"params": False}, in_axes=(0, 0))(c, name="vfe")
        x = vfe(points, valid)
        x = nn.relu(nn.Conv(c.channels[0], (3, 3), strides=2, name="stem")(x))
        for i, ch in enumerate(c.channels):
            x = ResBlock(ch, 2 if i == 2 else 1)(x)
        B = x.shape[0]
        x = nn.Dense(c.C)(x.reshape(B, -1, x.shape[-1]))
        return x + self.param("pos", nn.initializers.normal(0.02), (1, x.shape[1], c.C), F32)


class CrossLayer(nn.Module):
    """One MHAB layer (eq 5, 6) over keys ``kv`` (B, M, C) with ``kv_mask`` (B, M); a learned
    null key is always present."""

    C: int
    heads: int

    @nn.compact
    def __call__(self, q, kv, kv_mask):
        B = q.shape[0]
        null = self.param("null", nn.initializers.normal(0.02), (1, 1, self.C), F32)
        kv = jnp.concatenate([jnp.broadcast_to(null, (B, 1, self.C)), kv], 1)
        m = jnp.concatenate([jnp.ones((B, 1), bool), kv_mask], 1)
        a = nn.MultiHeadDotProductAttention(num_heads=self.heads, qkv_features=self.C)(q, kv, mask=m[:, None, None, :])
        q_att = nn.LayerNorm()(q + a)  # eq 5
        ffn = nn.Dense(self.C)(nn.relu(nn.Dense(2 * self.C)(q_att)))
        return nn.LayerNorm()(q_att + ffn)  # eq 6


class GRUHead(nn.Module):
    """One TFH head: query token (B, C) -> (B, horizon, 3) poses (x, y, φ) in the robot frame."""

    cfg: TPNConfig

    @nn.compact
    def __call__(self, q):
        c = self.cfg
        B = q.shape[0]
        h0 = jnp.tanh(nn.Dense(c.gru)(q))
        steps = self.param("steps", nn.initializers.normal(0.5), (c.horizon, 16), F32)
        inputs = jnp.concatenate([jnp.broadcast_to(steps, (B, c.horizon, 16)),
                                  jnp.broadcast_to(q[:, None, :], (B, c.horizon, q.shape[-1]))], -1)
        out = nn.RNN(nn.GRUCell(c.gru))(inputs, initial_carry=h0)
        inc = nn.Dense(3)(out) * c.step_scale
        return jnp.cumsum(inc, 1)


class TPN(nn.Module):
    """E_I (B, D), points (B, N, 4), points_valid (B, N), goal (B, GOAL_DIM), and per-sample
    modality switches use_image (B,), use_lidar (B,) bool -> τ^P (B, K, horizon, 3); with
    ``with_scores`` (needs ``cfg.score``), also the mode logits (B, K)."""

    cfg: TPNConfig

    @nn.compact
    def __call__(self, e_img, points, points_valid, goal, use_image, use_lidar, with_scores: bool = False):
        c = self.cfg
        B = e_img.shape[0]
        img = nn.Dense(c.img_tokens * c.C)(nn.relu(nn.Dense(c.C)(e_img))).reshape(B, c.img_tokens, c.C)
        lid = LidarEncoder(c)(points, points_valid)
        g = nn.relu(nn.Dense(c.C, name="goal_ffn")(goal))[:, None]  # single-layer FFN + ReLU
        q = jnp.broadcast_to(self.param("query", nn.initializers.normal(1.0), (1, c.K, c.C), F32), (B, c.K, c.C))
        q = CrossLayer(c.C, c.heads, name="sc_clip_attn")(q, img, jnp.broadcast_to(use_image[:, None], img.shape[:2]))
        q = CrossLayer(c.C, c.heads, name="lidar_attn")(q, lid, jnp.broadcast_to(use_lidar[:, None], lid.shape[:2]))
        q = CrossLayer(c.C, c.heads, name="goal_attn")(q, g, jnp.ones((B, 1), bool))
        # K GRU heads with separate weights (stacked on a leading axis), one per query token;
        # vmapped so that they compile once instead of K times
        heads = nn.vmap(GRUHead, variable_axes={"params": 0}, split_rngs={"params": True}, in_axes=1, out_axes=1,
                        axis_size=c.K)
        trajs = heads(c, name="tfh")(q)
        if not with_scores:
            return trajs
        if not c.score:
            return trajs, jnp.zeros(q.shape[:2], F32)
        # the plan itself is an input too: which head plays which manoeuvre varies from scene to scene
        z = jnp.concatenate([q, jax.lax.stop_gradient(trajs).reshape(B, c.K, -1)], -1)
        scores = nn.Dense(1, name="score_out")(nn.relu(nn.Dense(c.C, name="score_ffn")(z)))[..., 0]
        return trajs, scores


def init_tpn(key, cfg: TPNConfig = TPNConfig()):
    """Fresh TPN params (with the mode-score head when ``cfg.score``)."""
    z = jnp.zeros
    return jax.jit(partial(TPN(cfg).init, with_scores=True))(
        key, z((1, cfg.embed), F32), z((1, N_POINTS, 4), F32), z((1, N_POINTS), bool), z((1, cfg.goal_dim), F32),
        jnp.ones(1, bool), jnp.ones(1, bool))["params"]


def head_errors(pred, target, yaw_weight: float = 0.3):
    """(B, K) mean squared pose error of each head: pred (B, K, T, 3), target (B, T, 3) (m², with
    ``yaw_weight`` x rad² for the heading)."""
    d = pred[..., :2] - target[:, None, :, :2]
    dyaw = wrap_angle(pred[..., 2] - target[:, None, :, 2])
    return jnp.mean(jnp.sum(d ** 2, -1) + yaw_weight * dyaw ** 2, -1)


def wta_loss(pred, target, eps: float = 0.0, yaw_weight: float = 0.3):
    """eq 2, winner-takes-all: mean over the batch of the best head's error. With ``eps`` > 0,
    ``(1 - eps)`` x the winner's error + ``eps`` x the mean error of the others (relaxed WTA)."""
    err = head_errors(pred, target, yaw_weight)
    K = err.shape[1]
    best = jnp.min(err, 1)
    if eps <= 0 or K == 1:
        return jnp.mean(best)
    others = (jnp.sum(err, 1) - best) / (K - 1)
    return jnp.mean((1 - eps) * best + eps * others)


def score_loss(scores: jax.Array, pred: jax.Array, target: jax.Array) -> jax.Array:
    """Cross-entropy of the mode logits ``scores`` (B, K) against the WTA winner of ``pred``
    (B, K, T, 3) for ``target`` (B, T, 3) (no gradient through the winner's choice)."""
    k = jnp.argmin(jax.lax.stop_gradient(head_errors(pred, target)), 1)
    return -jnp.mean(jnp.take_along_axis(jax.nn.log_softmax(scores, -1), k[:, None], 1))


def make_loss_fn(cfg: TPNConfig = TPNConfig(), eps: float = 0.05, p_drop_image: float = 0.15,
                 p_drop_lidar: float = 0.15, score_weight: float = 0.02):
    """``loss(params, batch, key) -> ()`` (relaxed WTA, plus ``score_weight`` x the mode-score
    cross-entropy when ``cfg.score``) for batches ``{e_img, points, points_valid, goal, future}``;
    each sample drops E_I / E_L with the given probabilities (modality dropout, so that the
    ablations evaluate a network that has seen them missing)."""
    model = TPN(cfg)

    def loss(params, batch, key):
        B = batch["goal"].shape[0]
        k1, k2 = jax.random.split(key)
        use_i = jax.random.uniform(k1, (B,)) >= p_drop_image
        use_l = jax.random.uniform(k2, (B,)) >= p_drop_lidar
        pred, scores = model.apply({"params": params}, batch["e_img"], batch["points"], batch["points_valid"],
                                   batch["goal"], use_i, use_l, with_scores=True)
        out = wta_loss(pred, batch["future"], eps)
        if cfg.score:
            out = out + score_weight * score_loss(scores, pred, batch["future"])
        return out

    return loss


def predict(params, e_img, points, points_valid, goal, use_image=True, use_lidar=True, cfg: TPNConfig = TPNConfig()):
    """τ^P (B, K, horizon, 3) for a batch, with the modalities switched on or off for all samples."""
    B = goal.shape[0]
    return TPN(cfg).apply({"params": params}, e_img, points, points_valid, goal,
                          jnp.full((B,), use_image, bool), jnp.full((B,), use_lidar, bool))


def predict_scored(params, e_img, points, points_valid, goal, cfg: TPNConfig = TPNConfig()):
    """(τ^P (B, K, horizon, 3), mode logits (B, K)) for a batch, all modalities on."""
    B = goal.shape[0]
    on = jnp.ones((B,), bool)
    return TPN(cfg).apply({"params": params}, e_img, points, points_valid, goal, on, on, with_scores=True)


def closest_head(pred, target) -> np.ndarray:
    """(B,) index of the head closest to the target (what WTA trains)."""
    return np.asarray(jnp.argmin(head_errors(pred, target), 1))
