"""Preview images of a house: a labelled top-down map and a strip of sample frames."""

from __future__ import annotations

import os

import cv2
import numpy as np

from splatsearch.io import atomic_write_bytes

from .env import HouseEnv, camera_viewmat
from .house import House

_PALETTE = np.random.default_rng(7).uniform(40, 255, (4096, 3)).astype(np.uint8)


def instance_colors(ids: np.ndarray) -> np.ndarray:
    """(H, W) int ids -> (H, W, 3) uint8 colours (0 is black)."""
    out = _PALETTE[np.asarray(ids) % len(_PALETTE)].copy()
    out[np.asarray(ids) == 0] = 0
    return out


def depth_colors(depth: np.ndarray, max_depth: float = 5.0) -> np.ndarray:
    d = np.clip(depth / max_depth, 0, 1)
    img = cv2.applyColorMap((255 * (1 - d)).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[depth <= 0] = 0
    return img[..., ::-1]


def topdown_map(env: HouseEnv, px_per_m: int = 60) -> np.ndarray:
    """RGB uint8 map: unknown black, floor grey, navigable light, obstacles dark red, rooms outlined
    and named, objects boxed and labelled "class #id". North (+y) is up."""
    nav = env.nav
    img = np.zeros(nav.shape + (3,), np.uint8)
    img[nav.floor] = (110, 110, 110)
    img[nav.navigable] = (225, 225, 220)
    img[nav.obstacle] = (120, 30, 30)
    img = np.ascontiguousarray(img[::-1])  # grid row 0 is the smallest y: put +y up
    scale = px_per_m * nav.cell_size
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    Hp = img.shape[0]

    def to_px(x, y):
        return (int(round((x - nav.origin_xy[0]) * px_per_m)), int(round(Hp - 1 - (y - nav.origin_xy[1]) * px_per_m)))

    for r in env.house.rooms:
        cv2.rectangle(img, to_px(r.x0, r.y0), to_px(r.x1, r.y1), (60, 90, 200), 2)
        cv2.putText(img, f"{r.index}:{r.kind}", to_px(r.x0 + 0.15, r.y1 - 0.35), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    (40, 60, 160), 1, cv2.LINE_AA)
    for o in env.house.objects:
        c, h = o.center, o.size / 2
        col = tuple(int(v) for v in _PALETTE[o.instance_id % len(_PALETTE)])
        cv2.rectangle(img, to_px(c[0] - h[0], c[1] - h[1]), to_px(c[0] + h[0], c[1] + h[1]), col, 2)
        cv2.putText(img, f"{o.class_name} #{o.instance_id}", to_px(c[0] - h[0], c[1] - h[1] - 0.18),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def sample_frames(env: HouseEnv, n: int = 4, seed: int = 0) -> np.ndarray:
    """n rows of (RGB | depth | instances) from navigable poses facing each room's far side."""
    rng = np.random.default_rng(seed)
    cells = np.argwhere(env.nav.navigable)
    rows = []
    for _ in range(n):
        xy = env.nav.cell_to_world(cells[int(rng.integers(0, len(cells)))])
        f = env.render_view(camera_viewmat(xy[0], xy[1], float(rng.uniform(-np.pi, np.pi))))
        rows.append(np.concatenate([(f.rgb * 255).astype(np.uint8), depth_colors(f.depth, env.max_depth),
                                    instance_colors(f.instance)], 1))
    return np.concatenate(rows, 0)


def write_preview(house: House, out_dir: str, seed: int = 0, n_frames: int = 4) -> tuple[str, str]:
    """Write ``house_map.png`` and ``house_frames.png`` into ``out_dir``; returns both paths."""
    os.makedirs(out_dir, exist_ok=True)
    env = HouseEnv(house)
    paths = (os.path.join(out_dir, "house_map.png"), os.path.join(out_dir, "house_frames.png"))
    for path, img in zip(paths, (topdown_map(env), sample_frames(env, n_frames, seed))):
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))
        if not ok:
            raise RuntimeError(f"PNG encoding failed for {path}")
        atomic_write_bytes(path, buf.tobytes())
    return paths
