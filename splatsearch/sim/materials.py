"""Procedural materials: colour patterns evaluated at the world hit point by the renderer.

A material is a row of a :class:`MaterialTable`: two colours, a pattern, a frequency (1/m), a
noise amplitude and a seed. Patterns: 0 solid + noise, 1 checker, 2 stripes, 3 wood grain,
4 tiles with grout, 5 dots. Vertex-coloured meshes (a user's own) use material -1.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PATTERNS = ("solid", "checker", "stripes", "wood", "tiles", "dots")
VERTEX_COLOR = -1


@dataclass
class MaterialTable:
    """Columnar table of procedural materials (float32/int32 numpy arrays, one row each)."""

    color_a: list = field(default_factory=list)
    color_b: list = field(default_factory=list)
    pattern: list = field(default_factory=list)
    freq: list = field(default_factory=list)
    noise: list = field(default_factory=list)
    seed: list = field(default_factory=list)

    def add(self, color_a, color_b, pattern: str | int, freq: float, noise: float, seed: int) -> int:
        """Append a material and return its index."""
        p = PATTERNS.index(pattern) if isinstance(pattern, str) else int(pattern)
        self.color_a.append(np.clip(np.asarray(color_a, np.float32), 0, 1))
        self.color_b.append(np.clip(np.asarray(color_b, np.float32), 0, 1))
        self.pattern.append(p)
        self.freq.append(float(freq))
        self.noise.append(float(noise))
        self.seed.append(int(seed) & 0x7FFFFFFF)
        return len(self.pattern) - 1

    def __len__(self) -> int:
        return len(self.pattern)

    def arrays(self) -> dict[str, np.ndarray]:
        n = len(self)
        return {
            "color_a": np.asarray(self.color_a, np.float32).reshape(n, 3),
            "color_b": np.asarray(self.color_b, np.float32).reshape(n, 3),
            "pattern": np.asarray(self.pattern, np.int32).reshape(n),
            "freq": np.asarray(self.freq, np.float32).reshape(n),
            "noise": np.asarray(self.noise, np.float32).reshape(n),
            "seed": np.asarray(self.seed, np.int32).reshape(n),
        }

    def to_json(self) -> dict:
        return {k: v.tolist() for k, v in self.arrays().items()}

    @classmethod
    def from_json(cls, d: dict) -> MaterialTable:
        t = cls()
        for a, b, p, f, n, s in zip(d["color_a"], d["color_b"], d["pattern"], d["freq"], d["noise"], d["seed"]):
            t.add(a, b, int(p), f, n, s)
        return t


def random_material(rng: np.random.Generator, table: MaterialTable, *, kind: str = "object") -> int:
    """A distinct random material: saturated colours for objects, muted ones for rooms."""
    if kind == "object":
        hsv = np.array([rng.uniform(0, 1), rng.uniform(0.35, 0.95), rng.uniform(0.35, 0.95)])
    else:
        hsv = np.array([rng.uniform(0, 1), rng.uniform(0.05, 0.35), rng.uniform(0.55, 0.9)])
    a = hsv_to_rgb(hsv)
    b = hsv_to_rgb(np.array([(hsv[0] + rng.uniform(0.05, 0.5)) % 1.0, hsv[1] * rng.uniform(0.5, 1.0),
                             hsv[2] * rng.uniform(0.45, 0.85)]))
    pattern = int(rng.integers(0, len(PATTERNS)))
    freq = float(rng.uniform(2.0, 9.0) if kind == "object" else rng.uniform(1.0, 4.0))
    return table.add(a, b, pattern, freq, float(rng.uniform(0.03, 0.12)), int(rng.integers(0, 2**31 - 1)))


def hsv_to_rgb(hsv: np.ndarray) -> np.ndarray:
    h, s, v = float(hsv[0]), float(hsv[1]), float(hsv[2])
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i], np.float32)
