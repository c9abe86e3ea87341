"""CoNVOI's multi-modal visual marking (IV-B): candidates on O_t, line of sight, homography, numbers.

1. :func:`candidate_grid`: l rows x m columns of candidate points g_ij ahead of the robot, rows
   ``d_row`` apart along x, columns ``d_col`` apart along y (robot frame).
2. :func:`line_of_sight` (eq 2): g_ij is a candidate only if the line from the robot (the centre of
   O_t) to it crosses no occupied cell of O_t (obstacles inflated by the robot radius).
3. :func:`grid_to_image_homography` (eq 3): T_O^RGB, the homography from O_t's cells (col, row) to
   image pixels through the ground plane, built from the camera's intrinsics K, height and pitch
   (OpenCV camera frame: x right, y down, z forward).
4. :func:`mark`: numbers drawn with OpenCV at the projected candidates, ordered row by row
   (nearest row first) and left to right in the image, starting at 1.

:func:`render_view` makes the RGB image for the 2-D simulator: O_t's layers (floor, walls, people)
painted top-down and warped into the camera by the same homography, so image and grid agree by
construction (walls and people appear as their footprints: the image is schematic).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from splatsearch.nav.grid import GridSpec

from .perception import LocalMap


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera on the robot. K: (3, 3) intrinsics (pixels); width, height: pixels;
    height_m: camera height above the ground (m); pitch: radians, negative looks down;
    forward: camera position ahead of the robot centre (m)."""

    K: tuple = ((160.0, 0.0, 160.0), (0.0, 160.0, 120.0), (0.0, 0.0, 1.0))
    width: int = 320
    height: int = 240
    height_m: float = 0.6
    pitch: float = -0.35
    forward: float = 0.1

    def __post_init__(self):
        K = np.asarray(self.K, np.float64)
        if K.shape != (3, 3) or abs(np.linalg.det(K)) < 1e-9:
            raise ValueError(f"K must be an invertible 3x3 matrix, got {K.tolist()}")
        if self.width < 2 or self.height < 2 or self.height_m <= 0 or not -np.pi / 2 < self.pitch < np.pi / 2:
            raise ValueError("need width, height >= 2, height_m > 0 and |pitch| < pi/2")
        object.__setattr__(self, "K", tuple(map(tuple, K.tolist())))

    @classmethod
    def from_fov(cls, width: int = 320, height: int = 240, hfov_deg: float = 90.0, **kw) -> CameraModel:
        f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
        return cls(((f, 0, width / 2), (0, f, height / 2), (0, 0, 1)), width, height, **kw)

    @property
    def Kmat(self) -> np.ndarray:
        return np.asarray(self.K, np.float64)

    @property
    def hfov(self) -> float:
        """Horizontal field of view (rad)."""
        return float(2 * np.arctan(0.5 * self.width / self.Kmat[0, 0]))

    def viewmat(self) -> np.ndarray:
        """(4, 4) robot-frame-to-camera transform (OpenCV), the same construction as
        ``splatsearch.sim.camera_viewmat(forward, 0, 0, height_m, pitch)``."""
        p = self.pitch
        fwd = np.array([np.cos(p), 0.0, np.sin(p)])
        right = np.array([0.0, -1.0, 0.0])
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        vm = np.eye(4)
        vm[:3, :3] = R
        vm[:3, 3] = -R @ np.array([self.forward, 0.0, self.height_m])
        return vm

    def ground_homography(self) -> np.ndarray:
        """(3, 3) H with ``[u, v, 1] ~ H [x, y, 1]`` for robot-frame ground points (z = 0)."""
        vm = self.viewmat()
        return self.Kmat @ np.stack([vm[:3, 0], vm[:3, 1], vm[:3, 3]], 1)

    def project_ground(self, xy) -> tuple[np.ndarray, np.ndarray]:
        """Robot-frame ground points (..., 2) -> pixels (..., 2) and (...,) bool: in front of the
        camera and inside the image."""
        xy = np.asarray(xy, np.float64)
        h = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1) @ self.ground_homography().T
        w = h[..., 2]
        uv = h[..., :2] / np.where(np.abs(w) > 1e-12, w, 1e-12)[..., None]
        inside = (w > 1e-9) & (uv[..., 0] >= 0) & (uv[..., 0] < self.width) & (uv[..., 1] >= 0) & (uv[..., 1] < self.height)
        return uv, inside

    def unproject_pixels(self, uv) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (..., 2) -> robot-frame ground points (..., 2) and (...,) bool: the pixel's ray
        meets the ground in front of the camera (below the horizon)."""
        uv = np.asarray(uv, np.float64)
        Hinv = np.linalg.inv(self.ground_homography())
        g = np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], -1) @ Hinv.T
        w = g[..., 2]
        xy = g[..., :2] / np.where(np.abs(w) > 1e-12, w, 1e-12)[..., None]
        # the third row of H X is the camera depth of the ground point: > 0 means in front
        depth = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], -1) @ self.ground_homography()[2]
        return xy, (np.abs(w) > 1e-12) & (depth > 1e-9)


@dataclass(frozen=True)
class MarkerGrid:
    """l x m candidates: rows at x = first_row + i * d_row, columns at y = ((m - 1) / 2 - j) * d_col
    (j = 0 is the leftmost). The paper's outdoor values are l = 2..3, m = 6, d_row = 2.5 m,
    d_col = 2 m; indoors in our 2-D scenes we use a denser grid."""

    rows: int = 3
    cols: int = 7
    d_row: float = 1.0
    d_col: float = 0.45
    first_row: float = 1.0

    def __post_init__(self):
        if self.rows < 1 or self.cols < 1 or self.d_row <= 0 or self.d_col <= 0 or self.first_row <= 0:
            raise ValueError("need rows, cols >= 1 and positive spacings")


def candidate_grid(grid: MarkerGrid) -> np.ndarray:
    """(l, m, 2) robot-frame candidate points g_ij (m)."""
    x = grid.first_row + grid.d_row * np.arange(grid.rows)
    y = ((grid.cols - 1) / 2 - np.arange(grid.cols)) * grid.d_col
    X, Y = np.meshgrid(x, y, indexing="ij")
    return np.stack([X, Y], -1)


def line_of_sight(local_map: LocalMap, points) -> np.ndarray:
    """eq 2: (...,) bool, the straight line from the robot (0, 0) to each robot-frame point
    (..., 2) crosses no occupied cell of O_t and the point lies inside O_t."""
    pts = np.asarray(points, np.float64)
    flat = pts.reshape(-1, 2)
    step = 0.5 * local_map.spec.cell_size
    out = np.zeros(len(flat), bool)
    for k, p in enumerate(flat):
        n = max(2, int(np.ceil(np.linalg.norm(p) / step)) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        out[k] = bool(local_map.free_at(t * p[None]).all())
    return out.reshape(pts.shape[:-1])


def grid_to_image_homography(spec: GridSpec, camera: CameraModel) -> np.ndarray:
    """eq 3's T_O^RGB: (3, 3) mapping O_t cell coordinates [col, row, 1] (continuous, cell
    centres at +0.5 handled inside) to pixels [u, v, 1] up to scale."""
    c = spec.cell_size
    ox, oy = spec.origin_xy
    # (col, row) -> robot-frame (x, y): x = ox + (col + 0.5) c, y = oy + (row + 0.5) c
    A = np.array([[c, 0.0, ox + 0.5 * c], [0.0, c, oy + 0.5 * c], [0.0, 0.0, 1.0]])
    return camera.ground_homography() @ A


def apply_homography(H: np.ndarray, pts) -> np.ndarray:
    """(..., 2) points mapped by the 3x3 ``H`` (with the perspective divide)."""
    pts = np.asarray(pts, np.float64)
    h = np.concatenate([pts, np.ones(pts.shape[:-1] + (1,))], -1) @ np.asarray(H, np.float64).T
    return h[..., :2] / h[..., 2:3]


class Markers(NamedTuple):
    """The marked candidates X_t, in label order. labels: (K,) 1..K; robot_xy: (K, 2) m;
    cells: (K, 2) (row, col) in O_t; pixels: (K, 2) (u, v); row, col: (K,) grid indices (i, j)."""

    labels: np.ndarray
    robot_xy: np.ndarray
    cells: np.ndarray
    pixels: np.ndarray
    row: np.ndarray
    col: np.ndarray

    def lookup(self, labels) -> np.ndarray:
        """(n, 2) robot-frame points of the given marker labels, in the given order."""
        idx = {int(k): i for i, k in enumerate(self.labels)}
        missing = [int(k) for k in labels if int(k) not in idx]
        if missing:
            raise ValueError(f"labels {missing} are not marked (valid: {self.labels.tolist()})")
        return self.robot_xy[[idx[int(k)] for k in labels]].reshape(-1, 2)


def select_candidates(local_map: LocalMap, camera: CameraModel, grid: MarkerGrid) -> Markers:
    """X_t: the candidates that pass eq 2 and project into the image, numbered (see module doc)."""
    g = candidate_grid(grid)
    ok = line_of_sight(local_map, g)
    spec = local_map.spec
    rc = spec.world_to_cell(g)
    # eq 3 literally: cell coordinates through T_O^RGB
    H = grid_to_image_homography(spec, camera)
    cont = np.stack([(g[..., 0] - spec.origin_xy[0]) / spec.cell_size - 0.5,
                     (g[..., 1] - spec.origin_xy[1]) / spec.cell_size - 0.5], -1)
    uv = apply_homography(H, cont)
    _, visible = camera.project_ground(g)
    keep = ok & visible
    items = []
    for i in range(grid.rows):
        js = [j for j in range(grid.cols) if keep[i, j]]
        js.sort(key=lambda j: uv[i, j, 0])  # left to right in the image
        items += [(i, j) for j in js]
    K = len(items)
    ii = np.array([a for a, _ in items], np.int64)
    jj = np.array([b for _, b in items], np.int64)
    if K == 0:
        z2 = np.zeros((0, 2))
        return Markers(np.zeros(0, np.int64), z2, np.zeros((0, 2), np.int64), z2, ii, jj)
    return Markers(np.arange(1, K + 1), g[ii, jj], rc[ii, jj], uv[ii, jj], ii, jj)


def draw_markers(image: np.ndarray, markers: Markers, color=(255, 230, 0)) -> np.ndarray:
    """A uint8 copy of ``image`` with each marker's number drawn at its pixel (yellow, outlined)."""
    img = np.asarray(image)
    img = (np.clip(img, 0, 1) * 255).astype(np.uint8) if img.dtype != np.uint8 else img.copy()
    img = np.ascontiguousarray(img[..., :3])
    scale = max(0.35, img.shape[1] / 640.0)
    for lab, (u, v) in zip(markers.labels, markers.pixels):
        text = str(int(lab))
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        org = (round(u - tw / 2), round(v + th / 2))
        cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, tuple(int(c) for c in color), 1, cv2.LINE_AA)
    return img


def mark(image: np.ndarray, local_map: LocalMap, camera: CameraModel, grid: MarkerGrid) -> tuple[np.ndarray, Markers]:
    """I_t^Mark and X_t: select the candidates (eq 2, 3) and draw their numbers on ``image``."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[0] != camera.height or img.shape[1] != camera.width:
        raise ValueError(f"image must be ({camera.height}, {camera.width}, 3), got {img.shape}")
    markers = select_candidates(local_map, camera, grid)
    return draw_markers(img, markers), markers


FLOOR = (0.72, 0.70, 0.64)
WALL = (0.30, 0.30, 0.36)
SKY = (0.86, 0.88, 0.90)
PERSON_COLOURS = ((0.80, 0.20, 0.15), (0.15, 0.35, 0.80), (0.85, 0.55, 0.10), (0.45, 0.20, 0.60), (0.10, 0.55, 0.35))


def render_view(static_map: LocalMap, camera: CameraModel, people_robot=None, person_radius: float = 0.25,
                tile: float = 0.5) -> np.ndarray:
    """A schematic (H, W, 3) float32 RGB camera view of O_t: tiled floor, wall footprints, people
    discs (one colour each), warped into the image through the ground homography; above the
    horizon, a plain background."""
    spec = static_map.spec
    n_r, n_c = spec.shape
    xy = spec.cell_to_world(np.stack(np.meshgrid(np.arange(n_r), np.arange(n_c), indexing="ij"), -1))
    checker = ((np.floor(xy[..., 0] / tile) + np.floor(xy[..., 1] / tile)) % 2)[..., None]
    top = np.asarray(FLOOR, np.float32)[None, None] * (0.92 + 0.08 * checker)
    top = np.where((static_map.clearance <= 0)[..., None], np.asarray(WALL, np.float32), top)
    if people_robot is not None and len(people_robot):
        for k, p in enumerate(np.asarray(people_robot, np.float64).reshape(-1, 2)):
            inside = np.linalg.norm(xy - p, axis=-1) < person_radius
            top[inside] = PERSON_COLOURS[k % len(PERSON_COLOURS)]
    H = grid_to_image_homography(spec, camera)
    top = top.astype(np.float32)
    img = cv2.warpPerspective(top, H, (camera.width, camera.height), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=SKY)
    # pixels whose ray misses the ground ahead (above the horizon) get the background
    vv, uu = np.mgrid[0:camera.height, 0:camera.width]
    _, ground = camera.unproject_pixels(np.stack([uu + 0.5, vv + 0.5], -1))
    img[~ground] = SKY
    return np.clip(img, 0, 1)


def crop_patch(image: np.ndarray, center_uv, size: int) -> np.ndarray | None:
    """The ``size`` x ``size`` patch I^pat of ``image`` centred on pixel ``center_uv`` (clipped to
    the image), or None if the centre is outside it."""
    h, w = image.shape[:2]
    u, v = float(center_uv[0]), float(center_uv[1])
    if not (0 <= u < w and 0 <= v < h):
        return None
    half = size // 2
    r0, r1 = int(max(0, v - half)), int(min(h, v + half))
    c0, c1 = int(max(0, u - half)), int(min(w, u + half))
    if r1 <= r0 or c1 <= c0:
        return None
    return image[r0:r1, c0:c1]
