"""Live viser view of a social-navigation episode: walls, people, robot, paths and CoNVOI's image.

:class:`SocialViewer` binds to 127.0.0.1 (share button hidden), like
:class:`splatsearch.viewer.SearchViewer`, and never opens a browser, so it is safe on a headless
machine: print :attr:`SocialViewer.url` and connect when you want. Layers:

- ``walls``: the capsule obstacles as thick line segments;
- ``people``: one cylinder per pedestrian (seen ones bright, unseen ones grey), with group links;
- ``robot``: a cylinder and a heading arrow; ``rollout``: the DWA's chosen rollout;
- ``paths``: any number of named polylines (the robot's trajectory, the expert's, the global route);
- ``reference``: CoNVOI's reference path (points and legs);
- the GUI shows the status line, CoNVOI's last marked image, pause and speed controls.
"""

from __future__ import annotations

import threading
import time

import numpy as np

PERSON_HEIGHT = 1.7
ROBOT_HEIGHT = 0.4
COLOURS = {"dwa": (230, 60, 60), "convoi": (40, 170, 60), "expert": (60, 90, 230), "route": (170, 170, 170)}


class SocialViewer:
    """A viser server for one scene at a time.

    Args:
        port: TCP port on ``host`` (127.0.0.1 by default: local only).
        person_radius, robot_radius: metres, for the cylinders.
    """

    def __init__(self, port: int = 8080, host: str = "127.0.0.1", person_radius: float = 0.25,
                 robot_radius: float = 0.25, verbose: bool = False):
        import viser

        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server.gui.configure_theme(show_share_button=False)
        self.host, self.port = host, int(self.server.get_port())
        self.person_radius, self.robot_radius = float(person_radius), float(robot_radius)
        self._lock = threading.Lock()
        self._people: list = []
        self._handles: dict[str, list] = {}
        self._robot = None
        self._arrow = None
        gui = self.server.gui
        self.status = gui.add_markdown("**splatsearch social**: waiting")
        with gui.add_folder("Run"):
            self.pause = gui.add_checkbox("Pause", False)
            self.speed = gui.add_slider("Steps per second (0: max)", min=0.0, max=50.0, step=1.0, initial_value=20.0)
        self._image = gui.add_image(np.zeros((60, 80, 3), np.uint8), label="CoNVOI marked image")

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def _replace(self, layer: str, handles: list) -> None:
        for h in self._handles.get(layer, []):
            h.remove()
        self._handles[layer] = handles

    # -- layers -------------------------------------------------------------------------------
    def set_walls(self, capsules) -> None:
        """Obstacles (S, 5) rows (x1, y1, x2, y2, radius) in metres, drawn as segments."""
        caps = np.asarray(capsules, np.float32).reshape(-1, 5)
        with self._lock:
            handles = []
            walls = caps[np.linalg.norm(caps[:, 2:4] - caps[:, :2], axis=1) > 1e-6]
            if len(walls):
                seg = np.stack([np.c_[walls[:, :2], np.full(len(walls), 0.3)],
                                np.c_[walls[:, 2:4], np.full(len(walls), 0.3)]], 1)
                handles.append(self.server.scene.add_line_segments("/walls", seg, (40, 40, 60), thickness=0.1))
            for i, c in enumerate(caps[np.linalg.norm(caps[:, 2:4] - caps[:, :2], axis=1) <= 1e-6]):
                handles.append(self.server.scene.add_cylinder(f"/pillars/{i}", radius=float(c[4]), height=1.0,
                                                              color=(40, 40, 60), position=(c[0], c[1], 0.5)))
            self._replace("walls", handles)

    def set_people(self, positions, active=None, seen=None, groups=()) -> None:
        """People centres (P, 2) m; ``active`` (P,) which exist; ``seen`` (P,) which the robot
        perceives (drawn bright); ``groups``: tuples of indices linked by lines."""
        pos = np.asarray(positions, np.float32).reshape(-1, 2)
        n = len(pos)
        active = np.ones(n, bool) if active is None else np.asarray(active, bool)
        seen = active if seen is None else np.asarray(seen, bool)
        with self._lock:
            while len(self._people) < n:
                k = len(self._people)
                self._people.append(self.server.scene.add_cylinder(
                    f"/people/{k}", radius=self.person_radius, height=PERSON_HEIGHT, color=(230, 150, 40),
                    position=(0.0, 0.0, PERSON_HEIGHT / 2)))
            for k in range(n):
                h = self._people[k]
                h.visible = bool(active[k])
                if active[k]:
                    h.position = (float(pos[k, 0]), float(pos[k, 1]), PERSON_HEIGHT / 2)
                    h.color = (230, 150, 40) if seen[k] else (150, 150, 150)
            links = [(a, b) for g in groups for i, a in enumerate(g) for b in g[i + 1:] if active[a] and active[b]]
            handles = []
            if links:
                seg = np.array([[[*pos[a], 1.0], [*pos[b], 1.0]] for a, b in links], np.float32)
                handles.append(self.server.scene.add_line_segments("/groups", seg, (230, 150, 40), thickness=0.03))
            self._replace("groups", handles)

    def set_robot(self, pose) -> None:
        """The robot at ``pose`` (x, y, yaw) (m, rad)."""
        x, y, yaw = (float(v) for v in np.asarray(pose).reshape(-1)[:3])
        with self._lock:
            if self._robot is None:
                self._robot = self.server.scene.add_cylinder("/robot/body", radius=self.robot_radius, height=ROBOT_HEIGHT,
                                                             color=(30, 30, 30), position=(x, y, ROBOT_HEIGHT / 2))
            self._robot.position = (x, y, ROBOT_HEIGHT / 2)
            tip = np.array([[x, y, ROBOT_HEIGHT + 0.05], [x + 0.6 * np.cos(yaw), y + 0.6 * np.sin(yaw), ROBOT_HEIGHT + 0.05]])
            self._replace("heading", [self.server.scene.add_line_segments("/robot/heading", tip[None].astype(np.float32),
                                                                         (255, 255, 255), thickness=0.05)])

    def set_path(self, name: str, points_xy, color=(200, 200, 200), z: float = 0.03, thickness: float = 0.04) -> None:
        """A named polyline (N, 2) m on the ground (replaces the previous one of that name)."""
        pts = np.asarray(points_xy, np.float32).reshape(-1, 2)
        with self._lock:
            handles = []
            if len(pts) >= 2:
                p3 = np.c_[pts, np.full(len(pts), z, np.float32)]
                handles.append(self.server.scene.add_line_segments(f"/paths/{name}", np.stack([p3[:-1], p3[1:]], 1),
                                                                   color, thickness=thickness))
            self._replace(f"path:{name}", handles)

    def set_rollout(self, traj) -> None:
        """The DWA's chosen rollout (T, 3) or (T, 2)."""
        self.set_path("rollout", np.asarray(traj)[:, :2], (255, 220, 0), z=0.05, thickness=0.03)

    def set_reference(self, points_xy, robot_xy=None) -> None:
        """CoNVOI's reference path (K, 2) m: points and the legs from the robot through them."""
        pts = np.asarray(points_xy, np.float32).reshape(-1, 2)
        with self._lock:
            handles = []
            if len(pts):
                p3 = np.c_[pts, np.full(len(pts), 0.08, np.float32)]
                handles.append(self.server.scene.add_point_cloud("/reference/points", p3, (40, 200, 60), point_size=0.2,
                                                                 point_shape="circle"))
            self._replace("reference", handles)
        chain = pts if robot_xy is None else np.vstack([np.asarray(robot_xy, np.float32)[:2][None], pts])
        self.set_path("reference", chain, (40, 200, 60), z=0.07, thickness=0.03)

    def set_marked_image(self, image) -> None:
        """CoNVOI's last marked image (H, W, 3) uint8 or float in [0, 1]."""
        img = np.asarray(image)
        if img.dtype != np.uint8:
            img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
        self._image.image = np.ascontiguousarray(img[..., :3])

    def set_status(self, text: str) -> None:
        self.status.content = text

    def throttle(self) -> None:
        """Call once per step: waits while paused, then honours the speed slider."""
        while self.pause.value:
            time.sleep(0.05)
        sps = float(self.speed.value)
        if sps > 0:
            time.sleep(1.0 / sps)

    def close(self) -> None:
        self.server.stop()
