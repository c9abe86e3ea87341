"""Live viser viewer for a search episode: the Gaussian map, grid layers, plans and objects.

:class:`SearchViewer` owns a ``viser.ViserServer`` bound to 127.0.0.1 (share button hidden) and
exposes one ``set_*`` method per layer. Every method takes plain numpy arrays, so the viewer
depends on nothing but the map layout and can show any agent's state. Layers:

- ``map``: the Gaussian map, decimated to ``max_splats`` (most opaque x largest first);
- ``occupancy`` / ``value``: 2-D grids as textured ground planes, nearest-neighbour upsampled,
  unknown cells transparent;
- ``frontiers`` (the chosen one highlighted), ``path`` (FMM plan), ``trajectory``;
- ``camera``: the robot's frustum showing its current RGB;
- ``objects``: the object DB as boxes with labels and match scores;
- ``novel_views``: NVSM viewpoints as frustums, with rendered and inpainted thumbnails.

The GUI holds the goal image, pause / step / speed controls, layer toggles and a plot of the
best match score over time. An agent loop calls :meth:`SearchViewer.throttle` once per step: it
blocks while paused (one step per click on "Step") and sleeps according to the speed slider.
"""

from __future__ import annotations

import threading
import time

import numpy as np

LAYERS = ("map", "occupancy", "value", "frontiers", "path", "trajectory", "camera", "objects", "novel_views")
_GRID_Z = {"occupancy": 0.01, "value": 0.02}


def covariances_from(scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(N, 3, 3) world covariances R diag(s^2) R^T from scales (N, 3) metres and quats (N, 4) wxyz."""
    q = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    w, x, y, z = q.T
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
    M = R * scales[:, None, :]
    return (M @ np.swapaxes(M, 1, 2)).astype(np.float32)


def decimate(opacities: np.ndarray, scales: np.ndarray, budget: int) -> np.ndarray:
    """Indices of at most ``budget`` Gaussians, keeping those that cover the most
    (opacity x projected area ~ opacity x product of the two largest scales)."""
    n = len(opacities)
    if n <= budget:
        return np.arange(n)
    s = np.sort(scales, axis=1)
    score = opacities * s[:, 1] * s[:, 2]
    return np.sort(np.argpartition(-score, budget - 1)[:budget])


def grid_rgba(grid: np.ndarray, colors: dict[int, tuple[int, int, int, int]], upsample: int = 4) -> np.ndarray:
    """(H*u, W*u, 4) uint8 texture of an integer grid with a colour per value; values without
    a colour are transparent. viser lays an image's rows along its plane's +y, so grid row 0
    (smallest y) needs no flip."""
    out = np.zeros(grid.shape + (4,), np.uint8)
    for v, c in colors.items():
        out[grid == v] = c
    return _upsample(out, upsample)


def scalar_rgba(values: np.ndarray, known: np.ndarray, upsample: int = 4, alpha: int = 200) -> np.ndarray:
    """(H*u, W*u, 4) uint8 texture of a scalar grid in [0, 1] (turbo-like colour ramp);
    cells where ``known`` is False are transparent."""
    v = np.clip(np.nan_to_num(values), 0.0, 1.0)
    r = np.clip(1.5 - np.abs(4 * v - 3), 0, 1)
    g = np.clip(1.5 - np.abs(4 * v - 2), 0, 1)
    b = np.clip(1.5 - np.abs(4 * v - 1), 0, 1)
    out = np.zeros(values.shape + (4,), np.uint8)
    out[..., :3] = (np.stack([r, g, b], -1) * 255).astype(np.uint8)
    out[..., 3] = np.where(known, alpha, 0).astype(np.uint8)
    return _upsample(out, upsample)


def crop_known(known: np.ndarray, pad: int = 2) -> tuple[slice, slice] | None:
    """Row and column slices of the bounding box of ``known`` cells grown by ``pad`` (None if
    nothing is known): only that part of a large grid is worth sending to the browser."""
    rows = np.flatnonzero(known.any(1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(known.any(0))
    H, W = known.shape
    return (slice(max(0, rows[0] - pad), min(H, rows[-1] + pad + 1)),
            slice(max(0, cols[0] - pad), min(W, cols[-1] + pad + 1)))


def _upsample(img: np.ndarray, u: int) -> np.ndarray:
    # the browser samples textures bilinearly: repeating cells keeps their edges sharp
    return np.repeat(np.repeat(img, u, 0), u, 1) if u > 1 else img


def framing_camera(points: np.ndarray, fov: float = np.deg2rad(75.0), pitch_deg: float = 80.0,
                   margin: float = 1.3) -> tuple[np.ndarray, np.ndarray]:
    """(position, look_at) of a camera that shows all of ``points`` (N, 3) world metres.

    The camera looks down at ``pitch_deg`` below the horizon from the -y side, at the centre of
    the points' robust bounding box (2nd-98th percentile, so a few stray Gaussians do not push
    it away), far enough that the box's horizontal half-diagonal fits the vertical ``fov`` (rad)
    and at least 1 m above the highest point, so that walls do not hide the rooms inside them.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), 1)]
    if len(p) == 0:
        return np.array([3.0, -3.0, 4.0]), np.zeros(3)
    lo, hi = (np.percentile(p, [2, 98], axis=0) if len(p) >= 50 else (p.min(0), p.max(0)))
    look = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    radius = max(0.5 * float(np.hypot(hi[0] - lo[0], hi[1] - lo[1])), 1.0)
    pitch = np.deg2rad(pitch_deg)
    dist = max(margin * radius / np.tan(fov / 2), (hi[2] + 1.0 - look[2]) / np.sin(pitch))
    return look + dist * np.array([0.0, -np.cos(pitch), np.sin(pitch)]), look


def _pose_of(viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz, position) of a camera from its world-to-camera matrix (OpenCV frame, as viser's)."""
    import viser.transforms as vtf

    c2w = np.linalg.inv(np.asarray(viewmat, np.float64))
    return vtf.SO3.from_matrix(c2w[:3, :3]).wxyz, c2w[:3, 3]


class SearchViewer:
    """A viser server showing one search episode.

    Args:
        port: TCP port (bound on ``host``, 127.0.0.1 by default: the viewer is local only).
        max_splats: Gaussian budget per map update (~32 bytes each on the wire).
        grid_upsample: texture upsampling factor of the grid layers.
        max_z: Gaussians above this height (m) are not sent, so that the ceiling does not hide
            the rooms from the default top-down view; None sends everything.
        auto_frame: keep the initial camera framing the map and the robot as the map grows
            (browsers follow until their user moves the camera); see :meth:`frame`.

    Raises:
        ValueError: ``port`` outside 0..65535 (0: any free port), or ``max_splats`` < 1.
    """

    def __init__(self, port: int = 8080, host: str = "127.0.0.1", max_splats: int = 100_000,
                 grid_upsample: int = 2, max_z: float | None = 2.2, verbose: bool = False,
                 auto_frame: bool = True):
        import viser

        if max_splats < 1:
            raise ValueError(f"max_splats must be >= 1, got {max_splats}")
        check_port(port)
        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server.scene.set_up_direction("+z")
        self._frame: tuple[np.ndarray, np.ndarray] | None = None
        self._bounds: np.ndarray | None = None
        self._client_pose: dict[int, np.ndarray] = {}
        self.server.on_client_connect(lambda client: self._frame_client(client, force=True))
        self.server.gui.configure_theme(show_share_button=False)
        self.host, self.port = host, int(self.server.get_port())
        self.max_splats = int(max_splats)
        self.grid_upsample = int(grid_upsample)
        self.max_z = max_z
        self.auto_frame = bool(auto_frame)
        self._robot: np.ndarray | None = None
        self._splats = None
        self._lock = threading.Lock()
        self._step_requested = threading.Event()
        self._scores: list[tuple[float, float]] = []
        self._handles: dict[str, list] = {k: [] for k in LAYERS}
        self.update_seconds = 0.0

        gui = self.server.gui
        self.status = gui.add_markdown("**splatsearch**: waiting for the first step")
        self._goal = gui.add_image(np.zeros((48, 64, 3), np.uint8), label="goal image")
        with gui.add_folder("Run"):
            self.pause = gui.add_checkbox("Pause", False)
            step = gui.add_button("Step")
            self.speed = gui.add_slider("Steps per second (0: max)", min=0.0, max=20.0, step=0.5, initial_value=0.0)
        step.on_click(lambda _: self._step_requested.set())
        with gui.add_folder("Layers"):
            self.toggles = {}
            for name in LAYERS:
                cb = gui.add_checkbox(name.replace("_", " "), True)
                cb.on_update(lambda _, n=name: self._apply_visibility(n))
                self.toggles[name] = cb
        with gui.add_folder("Novel views", expand_by_default=False):
            self._nv_rendered = gui.add_image(np.zeros((48, 64, 3), np.uint8), label="best rendered view")
            self._nv_inpainted = gui.add_image(np.zeros((48, 64, 3), np.uint8), label="best inpainted view")
        self._plot = None
        self._plot_folder = gui.add_folder("Best match score")

    # -- helpers ------------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def frame(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Point the initial camera ("Reset View") at ``points`` (N, 3) metres, and move every
        browser whose camera is still where the viewer last put it (a user who moved the
        camera keeps their view). Returns (position, look_at)."""
        pos, look = framing_camera(points, fov=self.server.initial_camera.fov)
        self._frame = (pos, look)
        ic = self.server.initial_camera
        ic.up = (0.0, 0.0, 1.0)
        ic.look_at = look
        ic.position = pos
        for client in list(self.server.get_clients().values()):
            self._frame_client(client)
        return pos, look

    def _frame_client(self, client, force: bool = False) -> None:
        if self._frame is None:
            return
        last = self._client_pose.get(client.client_id)
        here = np.asarray(client.camera.position, np.float64)
        if not force and last is not None and np.linalg.norm(here - last) > 0.05:
            return  # the user has moved this camera
        pos, look = self._frame
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = pos  # moves look_at along with it: set look_at after
            client.camera.look_at = look
        self._client_pose[client.client_id] = pos

    def _auto_frame(self, means: np.ndarray) -> None:
        """Frame the map (and the robot) again when its bounding box has grown by > 0.5 m."""
        pts = means
        if self._robot is not None:
            pts = np.concatenate([means, self._robot[None]], 0)
        if len(pts) == 0:
            return
        b = np.concatenate([pts.min(0), pts.max(0)])
        if self._bounds is None or np.abs(b - self._bounds).max() > 0.5:
            self._bounds = b
            self.frame(pts)

    def _clear(self, layer: str) -> None:
        # before adding: viser replaces a node of the same name silently, and removing the old
        # handle afterwards would remove the new node
        for h in self._handles[layer]:
            h.remove()
        self._handles[layer] = []

    def _replace(self, layer: str, handles: list) -> None:
        self._handles[layer] = handles
        self._apply_visibility(layer)

    def _apply_visibility(self, layer: str) -> None:
        on = bool(self.toggles[layer].value)
        for h in self._handles[layer]:
            h.visible = on
        if layer == "map" and self._splats is not None:
            self._splats.visible = on

    def _timed(fn):  # noqa: N805 - decorator used inside the class body
        def wrapper(self, *a, **kw):
            t = time.perf_counter()
            with self._lock:
                out = fn(self, *a, **kw)
            self.update_seconds += time.perf_counter() - t
            return out

        wrapper.__doc__ = fn.__doc__
        wrapper.__name__ = fn.__name__
        return wrapper

    # -- layers -------------------------------------------------------------------------------
    @_timed
    def set_map(self, means: np.ndarray, scales: np.ndarray, quats: np.ndarray, opacities: np.ndarray,
                colors: np.ndarray) -> int:
        """Show the Gaussian map: means (N, 3) m, scales (N, 3) m, quats (N, 4) wxyz, opacities
        (N,) in [0, 1], colors (N, 3) in [0, 1]. Returns the number of splats sent."""
        means = np.asarray(means, np.float32)
        n = len(means)
        scales = np.broadcast_to(np.asarray(scales, np.float32).reshape(n, -1), (n, 3))
        opacities = np.asarray(opacities, np.float32).reshape(n)
        if self.max_z is not None:
            opacities = np.where(means[:, 2] > self.max_z, 0.0, opacities)
        keep = decimate(opacities, scales, self.max_splats)
        keep = keep[opacities[keep] > 0]
        cov = covariances_from(scales[keep], np.asarray(quats, np.float32)[keep])
        rgb = np.clip(np.asarray(colors, np.float32)[keep], 0, 1)
        op = opacities[keep, None]
        if self._splats is None:
            self._splats = self.server.scene.add_gaussian_splats("/map", centers=means[keep], covariances=cov,
                                                                 rgbs=rgb, opacities=op)
        else:
            self._splats.set_gaussians(means[keep], cov, rgb, op)
        self._apply_visibility("map")
        if self.auto_frame:
            self._auto_frame(means[keep])
        return len(keep)

    def set_gaussian_map(self, gmap) -> int:
        """Show a :class:`splatsearch.gaussians.GaussianMap` (active Gaussians only)."""
        m, q, s, o, c = (np.asarray(a) for a in gmap.render_args())
        act = np.asarray(gmap.active)
        return self.set_map(m[act], s[act], q[act], o[act], c[act])

    def _grid_plane(self, layer: str, rgba: np.ndarray, origin_xy, cell_size: float, shape) -> None:
        h, w = shape
        cx = origin_xy[0] + 0.5 * w * cell_size
        cy = origin_xy[1] + 0.5 * h * cell_size
        self._clear(layer)
        handle = self.server.scene.add_image(f"/{layer}", rgba, render_width=w * cell_size,
                                             render_height=h * cell_size, format="png",
                                             position=(cx, cy, _GRID_Z[layer]), cast_shadow=False,
                                             receive_shadow=False)
        self._replace(layer, [handle])

    @_timed
    def set_occupancy(self, grid: np.ndarray, origin_xy, cell_size: float, *, free: int = 1,
                      occupied: int = 2) -> None:
        """Occupancy grid (H, W) ints (grid[row, col] covers x = ox + col*c, y = oy + row*c);
        free cells light grey, occupied dark, anything else (unknown) transparent."""
        grid = np.asarray(grid)
        box = crop_known((grid == free) | (grid == occupied))
        if box is None:
            return
        sub = grid[box]
        origin = (origin_xy[0] + box[1].start * cell_size, origin_xy[1] + box[0].start * cell_size)
        rgba = grid_rgba(sub, {free: (225, 225, 225, 170), occupied: (40, 40, 60, 230)}, self.grid_upsample)
        self._grid_plane("occupancy", rgba, origin, cell_size, sub.shape)

    @_timed
    def set_value_map(self, value: np.ndarray, confidence: np.ndarray, origin_xy, cell_size: float) -> None:
        """Value map (H, W) in [0, 1] drawn where ``confidence`` > 0."""
        known_all = np.asarray(confidence) > 0
        box = crop_known(known_all)
        if box is None:
            return
        value = np.asarray(value, np.float32)[box]
        known = known_all[box]
        origin = (origin_xy[0] + box[1].start * cell_size, origin_xy[1] + box[0].start * cell_size)
        lo, hi = float(value[known].min()), float(value[known].max())
        norm = (value - lo) / max(hi - lo, 1e-6)
        self._grid_plane("value", scalar_rgba(norm, known, self.grid_upsample), origin, cell_size, value.shape)

    @_timed
    def set_frontiers(self, points_xy: np.ndarray, chosen: int | None = None, z: float = 0.05) -> None:
        """Frontier waypoints (K, 2) metres; ``chosen`` indexes the selected one."""
        sc = self.server.scene
        pts = np.asarray(points_xy, np.float32).reshape(-1, 2)
        handles = []
        self._clear("frontiers")
        if len(pts):
            p3 = np.c_[pts, np.full(len(pts), z, np.float32)]
            handles.append(sc.add_point_cloud("/frontiers/all", p3, (255, 160, 0), point_size=0.12,
                                              point_shape="circle"))
            if chosen is not None and 0 <= chosen < len(pts):
                handles.append(sc.add_point_cloud("/frontiers/chosen", p3[chosen:chosen + 1] + [0, 0, 0.01],
                                                  (255, 0, 80), point_size=0.3, point_shape="circle"))
        self._replace("frontiers", handles)

    def _polyline(self, layer: str, pts_xy: np.ndarray, color, z: float) -> None:
        pts = np.asarray(pts_xy, np.float32).reshape(-1, 2)
        handles = []
        self._clear(layer)
        if len(pts) >= 2:
            p3 = np.c_[pts, np.full(len(pts), z, np.float32)]
            seg = np.stack([p3[:-1], p3[1:]], 1)
            handles.append(self.server.scene.add_line_segments(f"/{layer}", seg, color, thickness=0.03))
        self._replace(layer, handles)

    @_timed
    def set_path(self, points_xy: np.ndarray) -> None:
        """The planned FMM path (P, 2) metres."""
        self._polyline("path", points_xy, (0, 200, 255), 0.06)

    @_timed
    def set_trajectory(self, points_xy: np.ndarray) -> None:
        """The robot's trajectory so far (T, 2) metres."""
        self._polyline("trajectory", points_xy, (230, 30, 30), 0.04)

    @_timed
    def set_camera(self, viewmat: np.ndarray, K: np.ndarray, rgb: np.ndarray | None = None) -> None:
        """The robot camera (world-to-camera ``viewmat``, intrinsics ``K``) with its RGB image."""
        wxyz, pos = _pose_of(viewmat)
        self._robot = np.asarray(pos, np.float32)
        K = np.asarray(K, np.float64)
        w, h = 2 * K[0, 2], 2 * K[1, 2]
        fov = 2 * np.arctan(h / (2 * K[1, 1]))
        img = None if rgb is None else _thumb(rgb, 160)
        self._clear("camera")
        handle = self.server.scene.add_camera_frustum("/camera", fov=float(fov), aspect=float(w / h), scale=0.3,
                                                      image=img, wxyz=wxyz, position=pos, color=(230, 30, 30))
        self._replace("camera", [handle])

    @_timed
    def set_objects(self, objects: list[dict]) -> None:
        """Object DB entries, each a dict with ``centroid`` (3,), ``extent`` (3,) metres,
        ``label``, ``score`` (best match count) and ``matched`` (bool)."""
        sc = self.server.scene
        handles = []
        self._clear("objects")
        for i, o in enumerate(objects):
            c = np.asarray(o["centroid"], np.float32)
            ext = np.maximum(np.asarray(o.get("extent", (0.4, 0.4, 0.4)), np.float32), 0.05)
            col = (0, 220, 90) if o.get("matched") else (255, 200, 0)
            handles.append(sc.add_box(f"/objects/{i}/box", color=col, dimensions=tuple(ext), wireframe=True,
                                      position=tuple(c)))
            text = f"{o.get('label', '?')} {int(o.get('score', 0))}"
            handles.append(sc.add_label(f"/objects/{i}/label", text, position=tuple(c + [0, 0, ext[2] / 2 + 0.1])))
        self._replace("objects", handles)

    @_timed
    def set_novel_views(self, viewmats: np.ndarray, K: np.ndarray, rendered: np.ndarray | None = None,
                        inpainted: np.ndarray | None = None, best: int | None = None) -> None:
        """NVSM viewpoints (N, 4, 4) as frustums with thumbnails of the rendered (N, H, W, 3)
        views; the GUI shows the best view rendered and inpainted."""
        K = np.asarray(K, np.float64)
        w, h = 2 * K[0, 2], 2 * K[1, 2]
        fov = 2 * np.arctan(h / (2 * K[1, 1]))
        handles = []
        self._clear("novel_views")
        for i, vm in enumerate(np.asarray(viewmats)):
            wxyz, pos = _pose_of(vm)
            img = None if rendered is None else _thumb(rendered[i], 64)
            col = (0, 220, 90) if i == best else (120, 120, 255)
            handles.append(self.server.scene.add_camera_frustum(f"/novel_views/{i}", fov=float(fov),
                                                                aspect=float(w / h), scale=0.15, image=img,
                                                                wxyz=wxyz, position=pos, color=col))
        self._replace("novel_views", handles)
        i = 0 if best is None else best
        if rendered is not None and len(rendered):
            self._nv_rendered.image = _thumb(rendered[i], 256)
        if inpainted is not None and len(inpainted):
            self._nv_inpainted.image = _thumb(inpainted[i], 256)

    def set_goal(self, rgb: np.ndarray) -> None:
        """The goal image (H, W, 3) in [0, 1] in the GUI panel."""
        self._goal.image = _thumb(rgb, 256)

    def set_status(self, text: str) -> None:
        """Markdown status line at the top of the panel."""
        self.status.content = text

    def add_match_score(self, step: int, score: float) -> None:
        """Append a point to the best-match-score plot."""
        from viser import uplot

        self._scores.append((float(step), float(score)))
        data = tuple(np.asarray(c, np.float64) for c in zip(*self._scores))
        if self._plot is None:
            with self._plot_folder:
                self._plot = self.server.gui.add_uplot(
                    data, (uplot.Series(label="step"), uplot.Series(label="matches", stroke="green", width=2)),
                    aspect=1.6)
        else:
            self._plot.data = data

    # -- run control --------------------------------------------------------------------------
    def throttle(self) -> None:
        """Call once per agent step: blocks while paused (until "Step" is clicked), then waits
        to honour the speed slider (0 = as fast as possible)."""
        while self.pause.value and not self._step_requested.is_set():
            time.sleep(0.05)
        self._step_requested.clear()
        sps = float(self.speed.value)
        if sps > 0:
            time.sleep(1.0 / sps)

    def close(self) -> None:
        """Stop the server."""
        self.server.stop()


def check_port(port: int) -> int:
    """``port`` as an int if it is a TCP port number (0..65535; 0 picks a free one).

    viser moves on to the next port when one is busy, but an out-of-range number kills its server
    thread and leaves the caller waiting forever, so it is refused here first.
    """
    if isinstance(port, bool) or not isinstance(port, (int, np.integer)):
        raise ValueError(f"port must be an integer in 0..65535, got {port!r}")
    if not 0 <= int(port) <= 65535:
        raise ValueError(f"port must be in 0..65535, got {port}")
    return int(port)


def _thumb(rgb: np.ndarray, width: int) -> np.ndarray:
    """uint8 copy of an image scaled to ``width`` pixels wide (nearest, cheap to send)."""
    import cv2

    img = np.asarray(rgb)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
    h, w = img.shape[:2]
    if w > width:
        img = cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)
