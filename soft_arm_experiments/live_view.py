"""The live view's content, ROS-free: the arm as a Foxglove 3D scene and its series as JSON.

The ``live_view`` node (:mod:`.live_view_node`) feeds :class:`LiveView` what the graph publishes and
serves what it makes on a Foxglove WebSocket server; the Foxglove app draws it (the layout
``config/foxglove_layout.json`` opens the same panels on a bag). Everything is in ``arm_base``,
positions in metres, times in seconds of the graph's clock (the messages' stamps).

The scene (``/view/scene``, foxglove.SceneUpdate), one entity each:

- ``arm``: the backbone as a tube, a truncated cone between consecutive backbone points whose radius
  follows the arm's taper (base to tip radius along the arc length);
- ``mocap``: the markers the mocap saw, as spheres; the unseen ones are not drawn where they were
  last seen, they are named in the entity's metadata (``unseen``: marker numbers from 1 at the base);
- ``estimate``: the shape estimate's markers, and the tip's uncertainty as an ellipsoid of one
  standard deviation along the principal axes of its covariance;
- ``target``: the goal's target, the task's coordinates over the marker they belong to (the axes
  the task leaves free taken from that marker as the mocap or the estimate last placed it);
- ``trail``: the tip's path over the last ``trail`` seconds.

The series (JSON): ``/view/tendons`` (shortening [m], rate [m/s], tension [N], reference shortening
[m] per tendon), ``/view/task`` (target, measured coordinates and their error [m]), and
``/view/diagnostics`` (each status's level, message and values).

:class:`LiveServer` serves them (the Foxglove SDK's WebSocket server, and an MCAP file if asked):
the node's and ``soft-arm-harness --live``'s.
"""
from __future__ import annotations

import ipaddress
import math
from collections import deque

import numpy as np

AXES = "xyz"

VIEW_SCHEMA = {
    "host": ("str", lambda v: bool(v), "an address to bind the viewer's server to (127.0.0.1: this "
                                       "computer only; another needs view.remote)"),
    "port": ("int", lambda v: 0 <= v <= 65535, "a TCP port in [0, 65535] (0: any free one)"),
    "remote": ("bool", None, "true or false: true lets view.host be an address other computers reach"),
    "rate": ("float", lambda v: 1 <= v <= 120, "a scene rate in [1, 120] Hz"),
    "trail": ("float", lambda v: 0 <= v <= 60, "a time in [0, 60] s of the tip's trail"),
    "backlog": ("int", lambda v: 1 <= v <= 100000,
                "a number of messages in [1, 100000] a viewer may fall behind before its oldest are dropped"),
    "record": ("str", None, "an MCAP file to write the view into as well (empty: none), opened in the "
                            "Foxglove app with the same layout"),
}


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address (or ``localhost``): reachable from this computer only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bind(host: str, remote: bool):
    """ValueError unless ``host`` is a loopback address (:func:`is_loopback`) or ``remote`` allows
    another: a viewer's server reachable from the network is asked for, never a default."""
    if not remote and not is_loopback(host):
        raise ValueError(f"view.host {host!r} is not a loopback address: set view.remote to true to serve "
                         "the live view beyond this computer")


def radii(points, base_radius: float, tip_radius: float) -> np.ndarray:
    """(P,) [m]: the arm's radius at each backbone point (P, 3) [m], linear in the arc length from
    the base radius to the tip radius."""
    points = np.asarray(points, dtype=float)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    share = arc / arc[-1] if arc[-1] > 0 else np.zeros_like(arc)
    return base_radius + (tip_radius - base_radius) * share


def _quaternion_z_to(direction) -> tuple:
    """(x, y, z, w): the rotation taking the z axis onto the unit vector ``direction``."""
    d = np.asarray(direction, dtype=float)
    w = 1.0 + d[2]
    if w < 1e-9:                                 # opposite to z: half a turn about x
        return 1.0, 0.0, 0.0, 0.0
    axis = np.array([-d[1], d[0], 0.0])          # z x d
    q = np.array([axis[0], axis[1], axis[2], w])
    q /= np.linalg.norm(q)
    return tuple(float(v) for v in q)


def _quaternion_of(rotation) -> tuple:
    """(x, y, z, w) of a rotation matrix (3, 3)."""
    R = np.asarray(rotation, dtype=float)
    if np.linalg.det(R) < 0:
        R = R.copy()
        R[:, 2] *= -1.0
    w = math.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    x = math.copysign(math.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2.0, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2.0, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2.0, R[1, 0] - R[0, 1])
    return x, y, z, w


def _timestamp(t: float):
    from foxglove.messages import Timestamp
    sec = math.floor(t)
    return Timestamp(sec=int(sec), nsec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def _pose(position, quaternion=(0.0, 0.0, 0.0, 1.0)):
    from foxglove.messages import Pose, Quaternion, Vector3
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = quaternion
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


def tube(points, point_radii, color=(0.9, 0.5, 0.1, 1.0)) -> list:
    """Cylinder primitives (truncated cones) between consecutive points (P, 3) [m] with the radii
    (P,) [m]: each centred on its segment, its z axis along it, its faces the two radii."""
    from foxglove.messages import Color, CylinderPrimitive, Vector3
    points, point_radii = np.asarray(points, dtype=float), np.asarray(point_radii, dtype=float)
    out = []
    for a in range(len(points) - 1):
        d = points[a + 1] - points[a]
        length = float(np.linalg.norm(d))
        if length <= 0.0:
            continue
        width = 2.0 * max(point_radii[a], point_radii[a + 1])
        out.append(CylinderPrimitive(
            pose=_pose(0.5 * (points[a] + points[a + 1]), _quaternion_z_to(d / length)),
            size=Vector3(x=width, y=width, z=length),
            bottom_scale=float(2.0 * point_radii[a] / width),
            top_scale=float(2.0 * point_radii[a + 1] / width),
            color=Color(r=color[0], g=color[1], b=color[2], a=color[3])))
    return out


def _spheres(points, diameter: float, color) -> list:
    from foxglove.messages import Color, SpherePrimitive, Vector3
    return [SpherePrimitive(pose=_pose(p), size=Vector3(x=diameter, y=diameter, z=diameter),
                            color=Color(r=color[0], g=color[1], b=color[2], a=color[3])) for p in points]


def ellipsoid(center, covariance, color=(0.1, 0.6, 0.9, 0.35)):
    """A sphere primitive shaped as the ellipsoid of one standard deviation of ``covariance`` (3, 3)
    [m^2] about ``center`` [m]: its axes the covariance's eigenvectors, its diameters twice the
    square roots of the eigenvalues."""
    from foxglove.messages import Color, SpherePrimitive, Vector3
    values, vectors = np.linalg.eigh(0.5 * (np.asarray(covariance, dtype=float)
                                            + np.asarray(covariance, dtype=float).T))
    size = 2.0 * np.sqrt(np.maximum(values, 0.0))
    return SpherePrimitive(pose=_pose(center, _quaternion_of(vectors)),
                           size=Vector3(x=float(size[0]), y=float(size[1]), z=float(size[2])),
                           color=Color(r=color[0], g=color[1], b=color[2], a=color[3]))


SERIES = ("tendons", "task", "diagnostics")


def json_safe(value):
    """``value`` with every number that is no finite float (NaN, infinity) as None: JSON has none."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class LiveServer:
    """A Foxglove WebSocket server on ``host``:``port`` (0: a free one; :attr:`address` says which),
    checked by :func:`check_bind` with ``remote``, dropping a viewer's oldest messages beyond
    ``backlog``; with ``record``, the same channels into that MCAP file too. :meth:`publish` sends
    a scene and the series; :meth:`close` stops both."""

    def __init__(self, host: str, port: int, remote: bool = False, backlog: int = 64, record: str = ""):
        import foxglove
        from foxglove.channels import SceneUpdateChannel
        check_bind(host, remote)
        self.context = foxglove.Context()
        self.server = foxglove.start_server(name="soft_arm", host=host, port=port, context=self.context,
                                            message_backlog_size=backlog)
        self.recording = foxglove.open_mcap(record, allow_overwrite=True, context=self.context) \
            if record else None
        self.scene_channel = SceneUpdateChannel("/view/scene", context=self.context)
        self.series = {name: foxglove.Channel(f"/view/{name}", context=self.context) for name in SERIES}
        self.address = f"ws://{host}:{self.server.port}"
        self.published = 0

    @property
    def port(self) -> int:
        return self.server.port

    def publish(self, view: "LiveView", series: dict):
        """The scene of ``view`` and the ``series`` (name -> JSON-able value), to whoever listens
        (nothing is built when no one does)."""
        import time
        now = time.time_ns()
        if self.scene_channel.has_sinks():
            self.scene_channel.log(view.scene(), log_time=now)
        for name, channel in self.series.items():
            value = series.get(name)
            if value is not None and channel.has_sinks():
                channel.log(json_safe(value), log_time=now)
        self.published += 1

    def close(self):
        self.server.stop()
        if self.recording is not None:
            self.recording.close()


class LiveView:
    """What the live view shows, updated by the ``take_*`` calls with the graph's messages (as
    arrays) and read by :meth:`scene`; ``base_radius`` and ``tip_radius`` [m] are the arm's,
    ``trail`` [s] the tip's path kept."""

    def __init__(self, base_radius: float, tip_radius: float, trail: float = 2.0):
        self.base_radius, self.tip_radius, self.trail = float(base_radius), float(tip_radius), float(trail)
        self.backbone = None                 # (P, 3) [m]
        self.backbone_source = ""            # what the backbone is (take_backbone)
        self.mocap = None                    # (n, 3) [m], NaN rows unseen
        self.estimate = None                 # (n, 3) [m], NaN rows not stood by
        self.tip_covariance = None           # (3, 3) [m^2]
        self.target = None                   # (labels, values [m])
        self._trail: deque = deque()         # (t [s], tip (3,) [m])
        self.t = 0.0

    def take_backbone(self, t: float, points, source: str = "simulator"):
        """The backbone points (P, 3) [m] at t [s]; ``source``: what they are (the simulator's arm,
        the estimate, the model at the reference), shown with the scene's ``arm``."""
        self.t = max(self.t, float(t))
        self.backbone = np.asarray(points, dtype=float).reshape(-1, 3)
        self.backbone_source = source
        if len(self.backbone):
            self._trail.append((float(t), self.backbone[-1].copy()))
        while self._trail and self._trail[0][0] < float(t) - self.trail:
            self._trail.popleft()

    def take_mocap(self, t: float, markers):
        self.t = max(self.t, float(t))
        self.mocap = np.asarray(markers, dtype=float).reshape(-1, 3)

    def take_estimate(self, t: float, markers, tip_covariance=None):
        self.t = max(self.t, float(t))
        self.estimate = np.asarray(markers, dtype=float).reshape(-1, 3)
        if tip_covariance is not None:
            self.tip_covariance = np.asarray(tip_covariance, dtype=float)

    def take_target(self, labels, values):
        self.target = (list(labels), np.asarray(values, dtype=float))

    def task(self) -> dict | None:
        """The task series now: the target, the coordinates the mocap measured and their error [m]
        (None: no target or no frame yet; an unseen coordinate is NaN)."""
        if self.target is None or self.mocap is None:
            return None
        labels, target = self.target
        measured = [float(self.mocap[int(label.split(".")[0][6:]) - 1, AXES.index(label[-1])])
                    for label in labels]
        return {"t": self.t, "labels": labels, "target": target.tolist(), "measured": measured,
                "error": [m - d for m, d in zip(measured, target)]}

    def target_points(self) -> np.ndarray:
        """(k, 3) [m]: one point per marker the target names; the axes it leaves free from where the
        mocap (else the estimate) last placed that marker (none without either)."""
        if self.target is None:
            return np.zeros((0, 3))
        labels, values = self.target
        known = self.mocap if self.mocap is not None else self.estimate
        points = {}
        for label, value in zip(labels, values):
            marker, axis = label.split(".")
            k = int(marker.replace("marker", "")) - 1
            if k not in points:
                base = known[k] if known is not None and k < len(known) else np.full(3, np.nan)
                points[k] = np.array(base, dtype=float)
            points[k][AXES.index(axis)] = value
        return np.array([p for p in points.values() if np.all(np.isfinite(p))]).reshape(-1, 3)

    def scene(self):
        """The scene now (foxglove.messages.SceneUpdate)."""
        from foxglove.messages import (Color, KeyValuePair, LinePrimitive, LinePrimitiveLineType, Point3,
                                       SceneEntity, SceneUpdate)
        stamp = _timestamp(self.t)
        entities = []

        def entity(name, metadata=(), **primitives):
            entities.append(SceneEntity(timestamp=stamp, frame_id="arm_base", id=name,
                                        metadata=[KeyValuePair(key=k, value=v) for k, v in metadata],
                                        **primitives))

        if self.backbone is not None and len(self.backbone) > 1:
            point_radii = radii(self.backbone, self.base_radius, self.tip_radius)
            entity("arm", metadata=[("source", self.backbone_source)],
                   cylinders=tube(self.backbone, point_radii))
        if self.mocap is not None:
            seen = np.all(np.isfinite(self.mocap), axis=1)
            unseen = ",".join(str(k + 1) for k in np.flatnonzero(~seen))
            entity("mocap", metadata=[("unseen", unseen)],
                   spheres=_spheres(self.mocap[seen], 0.012, (0.2, 0.9, 0.2, 1.0)))
        if self.estimate is not None:
            stood = np.all(np.isfinite(self.estimate), axis=1)
            spheres = _spheres(self.estimate[stood], 0.008, (0.1, 0.6, 0.9, 1.0))
            if self.tip_covariance is not None and stood[-1] and np.all(np.isfinite(self.tip_covariance)):
                spheres.append(ellipsoid(self.estimate[-1], self.tip_covariance))
            entity("estimate", spheres=spheres)
        targets = self.target_points()
        if len(targets):
            entity("target", spheres=_spheres(targets, 0.01, (0.9, 0.1, 0.1, 0.8)))
        if len(self._trail) > 1:
            entity("trail", lines=[LinePrimitive(
                type=LinePrimitiveLineType.LineStrip, pose=_pose((0.0, 0.0, 0.0)), thickness=0.002,
                scale_invariant=False, points=[Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                                               for _, p in self._trail],
                color=Color(r=0.9, g=0.9, b=0.2, a=0.8))])
        return SceneUpdate(entities=entities)
