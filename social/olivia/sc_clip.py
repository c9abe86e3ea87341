"""SC-CLIP (thesis 3.2.1.1, eq 3): the social-context image encoder (SCIE, F_I) and text encoder
(SCTE, F_T), and their contrastive loss with principal-component extraction (PCE).

* SCIE: a small ViT (patch embedding, CLS token, pre-LN transformer blocks) over the egocentric
  view (IMG_H, IMG_W, 3) -> E_I (D,). The thesis uses ViT-L/14; this is the same architecture at
  CPU scale (:class:`SCCLIPConfig` scales it up).
* SCTE: a transformer over word tokens (:mod:`splatsearch.social.olivia.tokenizer`) with a key-padding
  mask and masked mean pooling -> E_T (D,).
* eq 3: ``CE(F_I(I) · F_T(T_l)^T, labels) + CE(PCE(F_I(I)) · F_T(T_s)^T, labels)`` on unit
  vectors with a learnable logit scale (CLIP). The long caption aligns with the full image
  feature and the short caption with its coarse, principal-component part (Long-CLIP, thesis
  [76], [79]). ``labels`` are the matching indices; identical captions in a batch (templates
  repeat) share the target mass instead of being forced apart.

Everything is a pure function of a params pytree; shapes are static so ``jit`` compiles once.
"""

from __future__ import annotations

from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from .captions import LONG_LEN, SHORT_LEN
from .render import IMG_H, IMG_W
from .tokenizer import DEFAULT_TOKENIZER

F32 = jnp.float32


@dataclass(frozen=True)
class SCCLIPConfig:
    """img_h, img_w: input size (pixels); patch: ViT patch (pixels); width/depth/heads/mlp: the
    ViT; text_*: the text transformer; embed: D of E_I and E_T; vocab: token ids; text_len: the
    positional table (>= the longest caption); pce_k: principal components kept by PCE;
    init_temperature: initial CLIP temperature (logit scale = 1 / T)."""

    img_h: int = IMG_H
    img_w: int = IMG_W
    patch: int = 8
    width: int = 64
    depth: int = 2
    heads: int = 4
    mlp: int = 128
    text_width: int = 64
    text_depth: int = 2
    text_heads: int = 4
    text_mlp: int = 128
    embed: int = 64
    vocab: int = DEFAULT_TOKENIZER.vocab_size
    text_len: int = max(LONG_LEN, SHORT_LEN)
    pce_k: int = 16
    init_temperature: float = 0.07

    def __post_init__(self):
        if self.img_h % self.patch or self.img_w % self.patch:
            raise ValueError(f"image {self.img_h}x{self.img_w} is not divisible by the patch {self.patch}")
        if self.width % self.heads or self.text_width % self.text_heads:
            raise ValueError("widths must be divisible by the head counts")
        if not 0 < self.pce_k <= self.embed:
            raise ValueError(f"pce_k must be in 1..embed, got {self.pce_k}")


class Block(nn.Module):
    """Pre-LN transformer block: x + MHSA(LN x), then x + MLP(LN x). mask: (B, 1, L, L) bool."""

    width: int
    heads: int
    mlp: int

    @nn.compact
    def __call__(self, x, mask=None):
        h = nn.LayerNorm()(x)
        x = x + nn.MultiHeadDotProductAttention(num_heads=self.heads, qkv_features=self.width)(h, h, mask=mask)
        h = nn.LayerNorm()(x)
        h = nn.Dense(self.width)(nn.gelu(nn.Dense(self.mlp)(h)))
        return x + h


class SCIE(nn.Module):
    """Social context image encoder F_I: images (B, H, W, 3) uint8 or float in [0, 1] -> E_I (B, D)
    (not normalised)."""

    cfg: SCCLIPConfig

    @nn.compact
    def __call__(self, images):
        c = self.cfg
        x = images.astype(F32)
        x = jnp.where(images.dtype == jnp.uint8, x / 255.0, x)
        x = (x - 0.5) / 0.25
        x = nn.Conv(c.width, (c.patch, c.patch), strides=(c.patch, c.patch), padding="VALID", name="patch")(x)
        B = x.shape[0]
        x = x.reshape(B, -1, c.width)
        cls = self.param("cls", nn.initializers.normal(0.02), (1, 1, c.width), F32)
        x = jnp.concatenate([jnp.broadcast_to(cls, (B, 1, c.width)), x], 1)
        x = x + self.param("pos", nn.initializers.normal(0.02), (1, x.shape[1], c.width), F32)
        for _ in range(c.depth):
            x = Block(c.width, c.heads, c.mlp)(x)
        return nn.Dense(c.embed, use_bias=False, name="proj")(nn.LayerNorm()(x[:, 0]))


class SCTE(nn.Module):
    """Social context text encoder F_T: ids (B, L) int32 and mask (B, L) bool -> E_T (B, D)
    (not normalised). Padding never influences the output (key-padding mask, masked mean)."""

    cfg: SCCLIPConfig

    @nn.compact
    def __call__(self, ids, mask):
        c = self.cfg
        L = ids.shape[1]
        if L > c.text_len:
            raise ValueError(f"token length {L} exceeds the positional table {c.text_len}")
        x = nn.Embed(c.vocab, c.text_width)(ids)
        x = x + self.param("pos", nn.initializers.normal(0.02), (c.text_len, c.text_width), F32)[None, :L]
        att = mask[:, None, None, :] & mask[:, None, :, None]
        # a row with no valid key (a padded query) would be all -inf: let it see itself
        att = att | jnp.eye(L, dtype=bool)[None, None]
        for _ in range(c.text_depth):
            x = Block(c.text_width, c.text_heads, c.text_mlp)(x, att)
        x = nn.LayerNorm()(x)
        m = mask[..., None].astype(F32)
        pooled = jnp.sum(x * m, 1) / jnp.maximum(jnp.sum(m, 1), 1.0)
        return nn.Dense(c.embed, use_bias=False, name="proj")(pooled)


class SCCLIP(nn.Module):
    """The two encoders and the learnable log logit scale."""

    cfg: SCCLIPConfig

    def setup(self):
        self.image_encoder = SCIE(self.cfg)
        self.text_encoder = SCTE(self.cfg)
        self.log_scale = self.param("log_scale", lambda k: jnp.asarray(np.log(1.0 / self.cfg.init_temperature), F32))

    def encode_image(self, images):
        return self.image_encoder(images)

    def encode_text(self, ids, mask):
        return self.text_encoder(ids, mask)

    def __call__(self, images, long_ids, long_mask, short_ids, short_mask):
        return (self.image_encoder(images), self.text_encoder(long_ids, long_mask),
                self.text_encoder(short_ids, short_mask), self.log_scale)


def init_sc_clip(key, cfg: SCCLIPConfig = SCCLIPConfig()):
    """Fresh SC-CLIP params."""
    m = SCCLIP(cfg)
    img = jnp.zeros((1, cfg.img_h, cfg.img_w, 3), jnp.uint8)
    ids = jnp.zeros((1, 8), jnp.int32)
    mask = jnp.ones((1, 8), bool)
    # jitted: one compilation instead of op-by-op dispatch of every initialiser
    return jax.jit(m.init)(key, img, ids, mask, ids, mask)["params"]


def encode_images(params, images, cfg: SCCLIPConfig = SCCLIPConfig()) -> jax.Array:
    """(B, D) unit E_I of images (B, H, W, 3)."""
    return normalize(SCCLIP(cfg).apply({"params": params}, images, method=SCCLIP.encode_image))


def encode_texts(params, ids, mask, cfg: SCCLIPConfig = SCCLIPConfig()) -> jax.Array:
    """(B, D) unit E_T of token ids (B, L) with mask (B, L)."""
    return normalize(SCCLIP(cfg).apply({"params": params}, ids, mask, method=SCCLIP.encode_text))


def normalize(x, eps: float = 1e-6):
    """Unit vectors along the last axis."""
    return x / jnp.maximum(jnp.linalg.norm(x, axis=-1, keepdims=True), eps)


def pce(features, k: int):
    """Principal component extraction (Long-CLIP): features (B, D) reconstructed from their
    batch mean and top-``k`` principal directions, i.e. the coarse attributes shared across the
    batch. The basis is held constant under differentiation (SVD gradients are unstable when
    singular values meet); gradients flow through the projection."""
    x = features.astype(F32)
    mu = jnp.mean(x, 0, keepdims=True)
    xc = x - mu
    _, _, vt = jnp.linalg.svd(jax.lax.stop_gradient(xc), full_matrices=False)
    v = vt[:k].T  # (D, k)
    return mu + (xc @ v) @ v.T


def soft_targets(ids) -> jax.Array:
    """(B, B) row-normalised target matrix: 1 where two token rows are identical (the diagonal
    at least), so duplicate captions share the probability mass."""
    same = jnp.all(ids[:, None, :] == ids[None, :, :], -1).astype(F32)
    return same / jnp.sum(same, 1, keepdims=True)


def contrastive_ce(a, b, scale, targets=None, symmetric: bool = True):
    """CE of the logits ``scale · â b̂^T`` (a, b: (B, D), normalised here) against ``targets``
    (B, B) (default: the identity, labels = arange(B)); with ``symmetric`` the mean of the
    image->text and text->image directions (CLIP)."""
    a, b = normalize(a), normalize(b)
    logits = scale * a @ b.T
    B = a.shape[0]
    t = jnp.eye(B, dtype=F32) if targets is None else targets
    l1 = -jnp.mean(jnp.sum(t * jax.nn.log_softmax(logits, 1), 1))
    if not symmetric:
        return l1
    l2 = -jnp.mean(jnp.sum(t.T * jax.nn.log_softmax(logits.T, 1), 1))
    return 0.5 * (l1 + l2)


def sc_clip_loss(e_img, e_long, e_short, log_scale, long_ids=None, short_ids=None, pce_k: int = 16):
    """eq 3: CE(E_I · E_T(T_l)^T) + CE(PCE(E_I) · E_T(T_s)^T). Embeddings (B, D) need not be
    normalised; ``log_scale`` () is the log logit scale (clipped to 100 as in CLIP); the ids
    (B, L) mark duplicate captions (optional)."""
    scale = jnp.exp(jnp.minimum(log_scale, np.log(100.0)))
    tl = None if long_ids is None else soft_targets(long_ids)
    ts = None if short_ids is None else soft_targets(short_ids)
    return contrastive_ce(e_img, e_long, scale, tl) + contrastive_ce(pce(normalize(e_img), pce_k), e_short, scale, ts)


def make_loss_fn(cfg: SCCLIPConfig = SCCLIPConfig()):
    """``loss(params, batch) -> ()`` for batches ``{image, long_ids, long_mask, short_ids, short_mask}``."""
    model = SCCLIP(cfg)

    def loss(params, batch):
        e_i, e_l, e_s, ls = model.apply({"params": params}, batch["image"], batch["long_ids"], batch["long_mask"],
                                        batch["short_ids"], batch["short_mask"])
        return sc_clip_loss(e_i, e_l, e_s, ls, batch["long_ids"], batch["short_ids"], cfg.pce_k)

    return loss
