"""An offline word-level tokenizer for the SC-CLIP text encoder (SCTE).

It ships with the code: a fixed vocabulary (:data:`VOCAB`) covering the caption templates of
:mod:`splatsearch.social.olivia.dataset` and the everyday words a real VLM uses to describe people,
places and motion, plus ``n_hash`` hashed buckets for every other word. Hashing (a stable
FNV-1a, not Python's salted ``hash``) means a caption from a real VLM never fails to encode: an
unseen word lands in a bucket whose embedding the LLU can still learn.

Ids: 0 ``<pad>``, 1 ``<bos>``, 2 ``<eos>``, then the vocabulary, then the hash buckets.
:meth:`Tokenizer.encode` returns ``(ids, mask)`` padded/truncated to ``max_len`` (static shapes
for ``jit``); a truncated caption keeps ``<eos>`` as its last token.
"""

from __future__ import annotations

import re
from typing import Sequence

import numpy as np

PAD, BOS, EOS = 0, 1, 2
SPECIALS = ("<pad>", "<bos>", "<eos>")

# words of the caption templates first (so their ids never move), then general words
_TEMPLATE_WORDS = """
a about ahead an and approaching are area around as at avoid away back be behind berth beside between
blind both but by can careful carefully centre clear close closely coming continue corner corridor
could crossing curves distance do door doorway down dynamic each ensure far follow for from front
gap gently give going gradually group groups hallway has have heading in including into involves is
it its keep layout left let line looking maintain meters metre metres middle moving narrow navigate
navigating near nearby no not of on one open or other pass passing past path pathway people person
present provided right robot room route safe safely scenario shirt side sides slightly slow space
standing static steady straight sudden that the them there they three through to together toward
towards turn turning two up very walking wall walls way while wide with within yield you your
shirts pace your four five six seven eight nine ten several many few single alone pair
red blue orange purple green yellow black white grey gray brown pink
jacket coat dress shirt
of image view scene indoor indoors building hall lobby office
is are was were will should must
""".split()

_GENERAL_WORDS = """
above across after again against all almost along already also always among another any anyone
arm arms avoid bag bags before below bench bicycle bike both bottom box brief busy cart chair chairs
child children collide collision collisions column columns conversation counter crowd crowded curve
dark desk direction directly door doors drive edge elevator empty end enough entrance exit
face facing fast floor flower forward furniture glass go ground hand head here high hurry if
just kiosk large let light little long look low man men mind move movement much next obstacle
obstacles occupied off only opening out over panel pillar pillars plant planter plants pole quick
quickly rail ramp reach rather reduce shop shopping short sign sit sitting small so some soon speed
stairs stand stop stopped store street student students sudden table tables talk talking than then
these this those tight top train trash turns under until use wait waiting wheelchair where which
who woman women
""".split()

VOCAB: tuple[str, ...] = tuple(dict.fromkeys(_TEMPLATE_WORDS + _GENERAL_WORDS))
_WORD = re.compile(r"[a-z]+|\d+(?:\.\d+)?")


def _fnv1a(word: str) -> int:
    h = 0x811C9DC5
    for b in word.encode("utf-8"):
        h = ((h ^ b) * 0x01000193) & 0xFFFFFFFF
    return h


class Tokenizer:
    """Word-level tokenizer: lowercase words and numbers (``2.5`` is one token).

    Args:
        vocab: the word list (default :data:`VOCAB`); n_hash: buckets for unknown words (> 0).
    """

    def __init__(self, vocab: Sequence[str] = VOCAB, n_hash: int = 256):
        if n_hash < 1:
            raise ValueError(f"n_hash must be >= 1, got {n_hash}")
        words = list(dict.fromkeys(w.lower() for w in vocab))
        if any(not _WORD.fullmatch(w) for w in words):
            raise ValueError("vocabulary words must be lowercase letters or numbers")
        self.words = tuple(words)
        self.n_hash = int(n_hash)
        self.index = {w: i + len(SPECIALS) for i, w in enumerate(self.words)}

    @property
    def vocab_size(self) -> int:
        """Number of ids (specials + vocabulary + hash buckets)."""
        return len(SPECIALS) + len(self.words) + self.n_hash

    def split(self, text: str) -> list[str]:
        """The words of ``text`` (lowercase)."""
        if not isinstance(text, str):
            raise TypeError(f"text must be a str, got {type(text).__name__}")
        return _WORD.findall(text.lower())

    def word_id(self, word: str) -> int:
        """The id of one word: its vocabulary slot, else its hash bucket."""
        i = self.index.get(word)
        if i is not None:
            return i
        return len(SPECIALS) + len(self.words) + _fnv1a(word) % self.n_hash

    def unknown_words(self, text: str) -> list[str]:
        """Words of ``text`` that are not in the vocabulary (they will be hashed)."""
        return [w for w in self.split(text) if w not in self.index]

    def encode(self, text: str, max_len: int) -> tuple[np.ndarray, np.ndarray]:
        """``(ids (max_len,) int32, mask (max_len,) bool)``: ``<bos> words <eos>`` then padding."""
        if max_len < 3:
            raise ValueError(f"max_len must be >= 3, got {max_len}")
        ids = [BOS] + [self.word_id(w) for w in self.split(text)][: max_len - 2] + [EOS]
        out = np.full(max_len, PAD, np.int32)
        out[: len(ids)] = ids
        return out, out != PAD

    def encode_batch(self, texts: Sequence[str], max_len: int) -> tuple[np.ndarray, np.ndarray]:
        """(B, max_len) ids and mask for a list of texts."""
        if len(texts) == 0:
            return np.zeros((0, max_len), np.int32), np.zeros((0, max_len), bool)
        pairs = [self.encode(t, max_len) for t in texts]
        return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])

    def decode(self, ids) -> str:
        """Words of the ids (hash buckets read ``<hash:k>``; padding and specials dropped)."""
        out = []
        for i in np.asarray(ids).reshape(-1).tolist():
            if i < len(SPECIALS):
                continue
            j = i - len(SPECIALS)
            out.append(self.words[j] if j < len(self.words) else f"<hash:{j - len(self.words)}>")
        return " ".join(out)


DEFAULT_TOKENIZER = Tokenizer()
