"""On-disk cache of baseline and reference episodes for ``social eval`` (``--baseline-cache DIR``).

The reference walker, DWA and CoNVOI+DWA do not depend on the OLiVia-Nav checkpoint, so their
episodes on the held-out seeds are the same for every training. Re-running them for each of
three trainings (and twice per seed in Table II) is most of an evaluation's cost on 2 cores.

An entry is keyed by the planner kind, the scenario name, its seed, its geometry (m), the
episode cap and a SHA-256 digest of every ``.py`` file of :mod:`splatsearch.social.convoi`
(the code that builds the scenes and runs these planners). Editing any of those files changes
the digest, so stale episodes are never read back: they are simply not found (and stay on disk
until the directory is removed). The stored ``plan_ms`` is that of the run that filled the
entry.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
from collections.abc import Callable
from functools import lru_cache

from splatsearch.io import atomic_write_bytes

_CONVOI_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "convoi")


@lru_cache(maxsize=None)
def _digest_of(directory: str, stamp: tuple) -> str:
    h = hashlib.sha256()
    for name in sorted(n for n in os.listdir(directory) if n.endswith(".py")):
        h.update(name.encode())
        with open(os.path.join(directory, name), "rb") as f:
            h.update(f.read())
    return h.hexdigest()


def source_digest(directory: str = _CONVOI_DIR) -> str:
    """SHA-256 hex digest over the names and bytes of the ``.py`` files in ``directory``
    (default: the convoi package: scenarios, pedestrian simulator, DWA, CoNVOI, walker)."""
    stats = [(n, os.stat(os.path.join(directory, n))) for n in sorted(os.listdir(directory)) if n.endswith(".py")]
    return _digest_of(directory, tuple((n, st.st_mtime_ns, st.st_size) for n, st in stats))


def entry_key(scn, kind: str, digest: str | None = None) -> str:
    """Hex key of the episode of planner ``kind`` on scenario ``scn`` (its name, seed, geometry,
    ``max_steps`` and the convoi source digest)."""
    geo = scn._cache.get("geometry", {})
    spec = {"kind": kind, "scenario": scn.name, "seed": int(scn.seed), "max_steps": int(scn.max_steps),
            "geometry": {k: round(float(v), 6) for k, v in sorted(geo.items())},
            "source": digest or source_digest()}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()


class BaselineCache:
    """Episodes (:class:`~splatsearch.social.convoi.runner.EpisodeResult`) of the non-learned
    planners under ``directory``, one pickle per entry (``<kind>/<scenario>-<seed>-<key16>.pkl``).

    ``source_dir``: the sources whose digest keys the entries (default: the convoi package).
    ``hits`` / ``misses`` count look-ups since construction. The files are this program's own
    output: do not point ``directory`` at files from elsewhere (pickle runs code on load).
    """

    def __init__(self, directory: str, source_dir: str = _CONVOI_DIR):
        if not directory:
            raise ValueError("a baseline cache needs a directory")
        if os.path.exists(directory) and not os.path.isdir(directory):
            raise NotADirectoryError(f"baseline cache {directory!r} exists and is not a directory")
        self.directory = os.path.abspath(directory)
        self.source_dir = source_dir
        self.hits = 0
        self.misses = 0

    def path(self, scn, kind: str, key: str | None = None) -> str:
        """Where the entry of (``scn``, ``kind``) is stored (``key``: its :meth:`key`, if known)."""
        key = key or self.key(scn, kind)
        return os.path.join(self.directory, kind, f"{scn.name}-{int(scn.seed)}-{key[:16]}.pkl")

    def key(self, scn, kind: str) -> str:
        """:func:`entry_key` with this cache's source digest."""
        return entry_key(scn, kind, source_digest(self.source_dir))

    def get(self, scn, kind: str, run: Callable[[], object]):
        """The cached episode of ``kind`` on ``scn``, or ``run()``'s result, stored for next time.
        An unreadable entry (truncated, another format) counts as a miss and is overwritten."""
        key = self.key(scn, kind)
        p = self.path(scn, kind, key)
        if os.path.exists(p):
            try:
                with open(p, "rb") as f:
                    rec = pickle.load(f)
                if rec.get("key") == key:
                    self.hits += 1
                    return rec["episode"]
            except (OSError, EOFError, pickle.UnpicklingError, AttributeError, KeyError, TypeError, ValueError):
                pass
        self.misses += 1
        res = run()
        os.makedirs(os.path.dirname(p), exist_ok=True)
        atomic_write_bytes(p, pickle.dumps({"key": key, "episode": res},
                                           protocol=pickle.HIGHEST_PROTOCOL))
        return res
