"""OLiVia-Nav's Lifelong Learning Updater (LLU, thesis 3.2.1.2, eq 4).

During navigation the LLU stores images in a buffer of |B| images. When it is full, the images are
captioned by the large VLM (any :class:`~splatsearch.social.olivia.captions.Captioner`), and both
encoders are fine-tuned with the symmetric image-text loss of eq 4 at temperature μ:

    L = - Σ_{E_I ∈ V_I} log exp(h(E_I, E_T) / μ) / Σ_{E'_T ∈ V_T} exp(h(E_I, E'_T) / μ)

(h = cosine similarity; "symmetric" adds the same term with images and texts swapped). Then the
text database D_T (unit E_T of the long captions, plus their actions) is rebuilt with the new
F_T; it holds the offline captions and the buffer's new ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .captions import LONG_LEN, action_from_text
from .person_key import NO_PERSON, PERSON_DIM
from .sc_clip import SCCLIP, SCCLIPConfig, encode_texts, normalize, soft_targets
from .tokenizer import DEFAULT_TOKENIZER, Tokenizer

F32 = jnp.float32


def llu_loss(e_img, e_text, mu: float = 0.05, symmetric: bool = True, targets=None):
    """eq 4 averaged over the batch: e_img (B, D), e_text (B, D) (normalised here), matching rows.
    ``targets`` (B, B) optionally spreads the positive over identical captions; ``symmetric``
    averages the image->text and text->image terms."""
    if mu <= 0:
        raise ValueError(f"the temperature mu must be > 0, got {mu}")
    a, b = normalize(e_img), normalize(e_text)
    sim = a @ b.T / mu
    t = jnp.eye(a.shape[0], dtype=F32) if targets is None else targets
    l1 = -jnp.mean(jnp.sum(t * jax.nn.log_softmax(sim, 1), 1))
    if not symmetric:
        return l1
    return 0.5 * (l1 - jnp.mean(jnp.sum(t.T * jax.nn.log_softmax(sim.T, 1), 1)))


@dataclass
class TextDB:
    """D_T: unit text embeddings (N, D), their long captions and action indices (N,).

    ``keys`` (N, D) unit, optional: what E_I is compared with to retrieve each entry. None (the
    thesis): the text embeddings themselves. An LLU update (:func:`add_view_entries`) adds its
    buffer's captions keyed by the E_I of the views they describe, so that a view like one the
    update was given retrieves that caption at an image-to-image similarity near 1.

    ``persons`` (N, PERSON_DIM), optional: the perceived-person part of the key of each view
    entry (:func:`~splatsearch.social.olivia.person_key.person_state`; NaN rows: nobody ahead, and
    every row of an entry that is not a view's), used with ``OliviaConfig.person_key``."""

    embeddings: np.ndarray
    captions: list
    actions: np.ndarray
    keys: np.ndarray | None = None
    persons: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.embeddings)
        if len(self.captions) != n or len(self.actions) != n:
            raise ValueError(f"D_T needs one caption and one action per embedding: {n} embeddings, "
                             f"{len(self.captions)} captions, {len(self.actions)} actions")
        if self.keys is not None and np.shape(self.keys) != np.shape(self.embeddings):
            raise ValueError(f"D_T keys {np.shape(self.keys)} must match its embeddings {np.shape(self.embeddings)}")
        if self.persons is not None and np.shape(self.persons) != (n, PERSON_DIM):
            raise ValueError(f"D_T person keys {np.shape(self.persons)} must be ({n}, {PERSON_DIM})")

    @property
    def key_matrix(self) -> np.ndarray:
        """(N, D) the retrieval keys (the embeddings where no keys are stored)."""
        return self.embeddings if self.keys is None else self.keys

    def retrieve(self, e_img) -> tuple[int, np.ndarray]:
        """Index of the entry whose key is most cosine-similar to E_I (D,), and its E_T (D,)."""
        e = np.asarray(e_img, np.float32)
        e = e / max(float(np.linalg.norm(e)), 1e-6)
        i = int(np.argmax(self.key_matrix @ e))
        return i, self.embeddings[i]


def add_view_entries(db: TextDB, e_img: np.ndarray, e_text: np.ndarray, captions: list,
                     persons: np.ndarray | None = None) -> TextDB:
    """D_T plus one entry per buffer view: E_T ``e_text`` (B, D) of its caption, retrieved by the
    view's own E_I ``e_img`` (B, D) (both normalised here), and with ``persons`` (B, PERSON_DIM)
    also by the perceived person state there (:mod:`~splatsearch.social.olivia.person_key`).
    Duplicated captions stay, one per view: the same caption is right in several places."""
    if not (len(e_img) == len(e_text) == len(captions)):
        raise ValueError(f"need one E_I and one E_T per caption, got {len(e_img)}, {len(e_text)}, {len(captions)}")
    unit = lambda a: np.asarray(a, np.float32) / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-6)  # noqa: E731
    pers = None
    if persons is not None or db.persons is not None:
        old = db.persons if db.persons is not None else np.full((len(db.captions), PERSON_DIM), np.nan, np.float32)
        new = (np.asarray(persons, np.float32).reshape(len(captions), PERSON_DIM) if persons is not None
               else np.full((len(captions), PERSON_DIM), np.nan, np.float32))
        pers = np.concatenate([old, new])
    return TextDB(np.concatenate([db.embeddings, unit(e_text)]), list(db.captions) + list(captions),
                  np.concatenate([db.actions, [action_from_text(c) for c in captions]]).astype(np.int32),
                  np.concatenate([db.key_matrix, unit(e_img)]), pers)


def build_text_db(params, captions: list, cfg: SCCLIPConfig = SCCLIPConfig(), tok: Tokenizer = DEFAULT_TOKENIZER,
                  batch: int = 256) -> TextDB:
    """D_T from long captions with the current F_T (duplicates removed)."""
    caps = list(dict.fromkeys(captions))
    if not caps:
        raise ValueError("D_T needs at least one caption")
    f = jax.jit(lambda p, i, m: encode_texts(p, i, m, cfg))
    out = []
    for s in range(0, len(caps), batch):
        ids, mask = tok.encode_batch(caps[s:s + batch], min(LONG_LEN, cfg.text_len))
        out.append(np.asarray(f(params, jnp.asarray(ids), jnp.asarray(mask))))
    return TextDB(np.concatenate(out).astype(np.float32), caps, np.asarray([action_from_text(c) for c in caps], np.int32))


@dataclass
class LLUConfig:
    """size: |B| images per update; mu: eq 4 temperature; steps: optimiser steps per update;
    lr: AdamW learning rate; weight_decay; batch: images per step; view_entries: D_T also gets
    each buffer caption keyed by its view's E_I (:func:`add_view_entries`; False: the thesis'
    D_T, text keys only); tpn_encoder: which F_I gives the TPN its E_I after an update,
    "trained" (the F_I the TPN was trained with, kept as ``clip_tpn``; since stop 34) or
    "updated" (F_I^(i_t), as in the thesis: the update then changes the plans too); caption_keep
    (m): how far to the side the reference's 4 s future must end for a buffer view to be
    captioned keep left / right (only the LLU buffer's captions; training data and the TSM keep
    :data:`~splatsearch.social.olivia.features.KEEP_THRESHOLD`, 0.35 m, the default here)."""

    size: int = 50
    mu: float = 0.05
    steps: int = 30
    lr: float = 1e-4
    weight_decay: float = 0.01
    batch: int = 50
    view_entries: bool = True
    tpn_encoder: str = "trained"
    caption_keep: float = 0.35

    def __post_init__(self):
        if not self.caption_keep > 0:
            raise ValueError(f"LLUConfig.caption_keep must be > 0 m, got {self.caption_keep}")
        if self.tpn_encoder not in ("trained", "updated"):
            raise ValueError(f"LLUConfig.tpn_encoder must be 'trained' or 'updated', got {self.tpn_encoder!r}")


@dataclass
class LLUBuffer:
    """The image buffer B_I (and the captions B_T once captioned).

    ``oncoming`` holds, per image, how many people the robot saw walking head-on toward it
    (:func:`~splatsearch.social.olivia.planner.oncoming_count`). With ``lazy`` the scenes are
    stored as zero-argument callables and made only for the views kept (:meth:`select`): the
    captioner's label (the reference's rollout from that state) is the expensive part."""

    size: int = 50
    images: list = field(default_factory=list)
    scenes: list = field(default_factory=list)
    observations: list = field(default_factory=list)
    oncoming: list = field(default_factory=list)
    episodes: list = field(default_factory=list)
    lazy: bool = False
    persons: list = field(default_factory=list)

    def add(self, image: np.ndarray, scene=None, observation=None, oncoming: int = 0, episode: int = -1,
            person: np.ndarray | None = None) -> bool:
        """Store one image (H, W, 3) (and the privileged scene a template captioner needs, or with
        ``lazy`` a callable making it, and optionally the whole observation, to show what the
        update changes on these views; ``oncoming``: head-on people seen; ``episode``: its seed;
        ``person``: (PERSON_DIM,) the perceived person state, NaN / None: nobody ahead);
        returns True when the buffer is full."""
        if len(self.images) < self.size:
            self.images.append(np.asarray(image))
            self.scenes.append(scene)
            self.observations.append(observation)
            self.oncoming.append(int(oncoming))
            self.episodes.append(int(episode))
            self.persons.append(NO_PERSON.copy() if person is None else np.asarray(person, np.float32))
        return self.full

    @property
    def full(self) -> bool:
        return len(self.images) >= self.size

    def select(self, idx, size: int | None = None) -> "LLUBuffer":
        """A (non-lazy) buffer of the views ``idx`` (in that order); lazy scenes are made here."""
        out = LLUBuffer(size or len(idx))
        for i in idx:
            sc = self.scenes[i]
            out.add(self.images[i], sc() if self.lazy and callable(sc) else sc, self.observations[i],
                    self.oncoming[i], self.episodes[i], self.persons[i])
        return out

    def clear(self) -> None:
        for a in (self.images, self.scenes, self.observations, self.oncoming, self.episodes, self.persons):
            a.clear()


def llu_update(params, images: np.ndarray, captions: list, cfg: LLUConfig = LLUConfig(),
               clip_cfg: SCCLIPConfig = SCCLIPConfig(), tok: Tokenizer = DEFAULT_TOKENIZER, seed: int = 0):
    """One LLU iteration i -> i+1: fine-tune F_I and F_T on (images (N, H, W, 3), long captions)
    with eq 4. Returns (new params, per-step losses)."""
    if len(images) != len(captions) or len(images) < 2:
        raise ValueError(f"need >= 2 images with one caption each, got {len(images)} and {len(captions)}")
    model = SCCLIP(clip_cfg)
    ids, mask = tok.encode_batch(list(captions), min(LONG_LEN, clip_cfg.text_len))
    imgs = np.asarray(images)

    def loss(p, im, i, m):
        e_i = model.apply({"params": p}, im, method=SCCLIP.encode_image)
        e_t = model.apply({"params": p}, i, m, method=SCCLIP.encode_text)
        return llu_loss(e_i, e_t, cfg.mu, True, soft_targets(i))

    opt = optax.adamw(cfg.lr, weight_decay=cfg.weight_decay)
    state = opt.init(params)

    @jax.jit
    def step(p, s, im, i, m):
        lv, g = jax.value_and_grad(loss)(p, im, i, m)
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s, lv

    rng = np.random.default_rng(seed)
    n = len(imgs)
    bs = min(cfg.batch, n)
    losses = []
    for _ in range(cfg.steps):
        sel = rng.permutation(n)[:bs]
        params, state, lv = step(params, state, jnp.asarray(imgs[sel]), jnp.asarray(ids[sel]), jnp.asarray(mask[sel]))
        losses.append(float(lv))
    return params, losses
