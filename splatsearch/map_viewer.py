"""``splatsearch view``: a saved Gaussian map in the browser, with map controls.

:class:`MapViewer` shows one :class:`~splatsearch.gaussians.GaussianMap` on a viser server bound to
127.0.0.1, framed by the initial camera. Its panel holds what a map viewer needs (as the gsplat
and nerfview viewers have): the splat count, a render mode, a splat budget, a height cut and the
background colour.

Render modes:
- ``RGB``: the browser draws the splats itself (viser's WebGL splatting), decimated to the budget;
- ``depth`` / ``alpha``: splatsearch's own rasterizer renders the *whole* map (no budget) from each
  browser's camera on this machine, and the picture is sent as that browser's background image
  (expected depth with a turbo colour ramp; accumulated opacity in grey). A new camera pose
  replaces a render still waiting, so a slow CPU render never queues up.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from splatsearch.viewer import check_port, covariances_from, decimate, framing_camera

RENDER_MODES = ("RGB", "depth", "alpha")
logger = logging.getLogger(__name__)


def client_camera(wxyz, position, fov: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(viewmat (4, 4), K (3, 3)) of a browser camera: orientation ``wxyz`` and ``position`` of the
    camera in the world (OpenCV frame, as viser's), vertical ``fov`` (rad), image ``width`` x
    ``height`` pixels with the principal point at the centre."""
    import viser.transforms as vtf

    c2w = np.eye(4)
    c2w[:3, :3] = vtf.SO3(np.asarray(wxyz, np.float64)).as_matrix()
    c2w[:3, 3] = np.asarray(position, np.float64)
    fy = 0.5 * height / np.tan(0.5 * fov)
    K = np.array([[fy, 0, 0.5 * width], [0, fy, 0.5 * height], [0, 0, 1]], np.float32)
    return np.linalg.inv(c2w).astype(np.float32), K


def render_view(gaussians: tuple, viewmat: np.ndarray, K: np.ndarray, width: int, height: int,
                mode: str) -> np.ndarray:
    """(height, width, 3) uint8 picture of ``gaussians`` = (means, quats, scales, opacities,
    colors) for ``mode``: "RGB" colours on black, "depth" expected depth (near = warm, far =
    cold, no Gaussian = black), "alpha" accumulated opacity in grey."""
    import cv2

    from splatsearch.rasterization import rasterize

    if mode not in RENDER_MODES:
        raise ValueError(f"mode must be one of {RENDER_MODES}, got {mode!r}")
    means, quats, scales, opac, colors = gaussians
    out = rasterize(means, quats, scales, opac, colors, viewmat, K, width, height, render_mode="RGB+ED")
    alpha = np.asarray(out.alpha)[..., 0]
    if mode == "RGB":
        img = np.asarray(out.image)
    elif mode == "alpha":
        img = np.repeat(alpha[..., None], 3, -1)
    else:
        depth = np.asarray(out.depth)[..., 0]
        seen = (alpha > 0.05) & np.isfinite(depth) & (depth > 0)
        if seen.any():
            lo, hi = np.percentile(depth[seen], [2, 98])
            t = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
        else:
            t = np.zeros_like(depth)
        ramp = cv2.applyColorMap(((1 - t) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
        img = np.where(seen[..., None], ramp / 255.0, 0.0)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


class MapViewer:
    """A viser server showing one Gaussian map with map controls.

    Args:
        gmap: the map (:class:`~splatsearch.gaussians.GaussianMap`; active Gaussians are shown).
        port: TCP port on ``host`` (0..65535; 0 picks a free one; a busy port moves to the next).
        max_splats: initial budget of splats sent to the browser in RGB mode.
        max_z: initial height cut (m): Gaussians above it are hidden (ceilings); None: no cut.
        render_width: width in pixels of the depth / alpha renders (height from the browser's aspect).
    """

    def __init__(self, gmap, port: int = 8080, host: str = "127.0.0.1", max_splats: int = 200_000,
                 max_z: float | None = None, render_width: int = 480, verbose: bool = False):
        import viser

        if max_splats < 1:
            raise ValueError(f"max_splats must be >= 1, got {max_splats}")
        check_port(port)
        act = np.asarray(gmap.active)
        if not act.any():
            raise ValueError("the map has no active Gaussians to show")
        m, q, s, o, c = (np.asarray(a) for a in gmap.render_args())
        self.means, self.quats, self.scales = m[act].astype(np.float32), q[act].astype(np.float32), s[act]
        self.opacities, self.colors = o[act].astype(np.float32), np.clip(c[act], 0, 1).astype(np.float32)
        self.scales = np.broadcast_to(self.scales.reshape(len(self.means), -1), (len(self.means), 3)).astype(np.float32)
        self.n_total = len(self.means)
        self.render_width = int(render_width)
        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server.gui.configure_theme(show_share_button=False)
        self.server.scene.set_up_direction("+z")
        self.host, self.port = host, int(self.server.get_port())
        self._splats = None
        self._lock = threading.Lock()
        self._pending: dict[int, object] = {}
        self._wake = threading.Event()
        self._closed = False
        self.n_shown = 0
        self.renders = 0

        z_lo, z_hi = float(self.means[:, 2].min()), float(self.means[:, 2].max())
        gui = self.server.gui
        self.info = gui.add_markdown("")
        self.mode = gui.add_dropdown("Render mode", RENDER_MODES, initial_value="RGB",
                                     hint="RGB: splats drawn by the browser; depth / alpha: rendered by "
                                          "splatsearch's rasterizer from your camera")
        self.budget = gui.add_slider("Splat budget", min=1_000, max=max(self.n_total, 1_001), step=1_000,
                                     initial_value=min(max_splats, self.n_total),
                                     hint="most covering splats sent to the browser in RGB mode")
        top = z_hi if max_z is None else float(np.clip(max_z, z_lo, z_hi))
        self.max_z = gui.add_slider("Max height (m)", min=round(z_lo, 2), max=round(z_hi, 2) + 0.01, step=0.05,
                                    initial_value=round(top, 2) + (0.01 if max_z is None else 0.0),
                                    hint="hide Gaussians above this height, e.g. ceilings")
        self.background = gui.add_rgb("Background", (255, 255, 255))
        self.mode.on_update(lambda _: self._refresh())
        self.budget.on_update(lambda _: self._send_splats())
        self.max_z.on_update(lambda _: self._refresh())
        self.background.on_update(lambda _: self._set_background())

        self.frame_pos, self.frame_look = framing_camera(self.means[self.means[:, 2] <= self.max_z.value],
                                                         fov=self.server.initial_camera.fov)
        ic = self.server.initial_camera
        ic.up = (0.0, 0.0, 1.0)
        ic.look_at = self.frame_look
        ic.position = self.frame_pos
        self.server.on_client_connect(self._on_connect)
        self._worker = threading.Thread(target=self._render_loop, daemon=True)
        self._worker.start()
        self._send_splats()
        self._set_background()

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    # -- browser splats (RGB mode) -------------------------------------------------------------
    def _visible(self) -> np.ndarray:
        return self.means[:, 2] <= float(self.max_z.value)

    def _send_splats(self) -> None:
        with self._lock:
            vis = np.flatnonzero(self._visible())
            keep = vis[decimate(self.opacities[vis], self.scales[vis], int(self.budget.value))]
            cov = covariances_from(self.scales[keep], self.quats[keep])
            args = (self.means[keep], cov, self.colors[keep], self.opacities[keep, None])
            if self._splats is None:
                self._splats = self.server.scene.add_gaussian_splats("/map", centers=args[0], covariances=args[1],
                                                                     rgbs=args[2], opacities=args[3])
            else:
                self._splats.set_gaussians(*args)
            self._splats.visible = self.mode.value == "RGB"
            self.n_shown = len(keep)
            self._update_info()

    def _update_info(self) -> None:
        mode = self.mode.value
        shown = (f"{self.n_shown:,} of {self.n_total:,} Gaussians drawn by the browser" if mode == "RGB"
                 else f"all {int(self._visible().sum()):,} Gaussians below the height cut, rendered here")
        self.info.content = f"**{mode}** · {shown}"

    def _set_background(self) -> None:
        if self.mode.value == "RGB":
            solid = np.broadcast_to(np.asarray(self.background.value, np.uint8), (4, 4, 3)).copy()
            self.server.scene.set_background_image(solid, format="png")
            for client in self.server.get_clients().values():  # replaces a depth / alpha render
                client.scene.set_background_image(solid, format="png")

    def _refresh(self) -> None:
        self._send_splats()
        if self.mode.value == "RGB":
            self._set_background()
        else:
            for client in self.server.get_clients().values():
                self._request(client)

    # -- server-side renders (depth / alpha) ---------------------------------------------------
    def _on_connect(self, client) -> None:
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = self.frame_pos  # moves look_at along: set it after
            client.camera.look_at = self.frame_look
        client.camera.on_update(lambda _: self._request(client))

    def _request(self, client) -> None:
        if self.mode.value != "RGB":
            with self._lock:
                self._pending[client.client_id] = client
            self._wake.set()

    def _render_loop(self) -> None:
        while not self._closed:
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                jobs, self._pending = list(self._pending.values()), {}
            for client in jobs:
                try:
                    self.render_for(client)
                except Exception as e:  # a browser that left mid-render, say; keep serving the others
                    if not self._closed:
                        logger.warning("render failed: %s: %s", type(e).__name__, e)

    def render_for(self, client) -> np.ndarray:
        """Render the current mode from ``client``'s camera and send it as its background image."""
        cam = client.camera
        w = self.render_width
        h = max(16, int(round(w / max(cam.aspect, 1e-3))))
        viewmat, K = client_camera(cam.wxyz, cam.position, cam.fov, w, h)
        vis = self._visible()
        gauss = (self.means[vis], self.quats[vis], self.scales[vis], self.opacities[vis], self.colors[vis])
        img = render_view(gauss, viewmat, K, w, h, self.mode.value)
        client.scene.set_background_image(img, format="jpeg")
        self.renders += 1
        return img

    def close(self) -> None:
        """Stop the render thread and the server."""
        self._closed = True
        self._wake.set()
        self.server.stop()
