"""The mocap bridge's configuration (``rig.mocap`` of ``config/mocap.yaml``, validated with
:data:`MOCAP_SCHEMA`; a bad value names ``rig.mocap.<key>``, the value and what is allowed) and the
calibration from the mocap system's frame into ``arm_base``.
"""
from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass
from functools import cached_property
from typing import Mapping, Optional, Sequence

import numpy as np

from soft_arm_model.parameters import (ConfigError, apply_overrides, default_config_dir, read_parameters,
                                       validate_tree)

from .clock_map import MAX_DELAY
from .natnet import SUPPORTED_VERSIONS, Version

NAMESPACE = "rig"
SOURCES = ("rigid_bodies", "labeled_markers")
VERSION_NAMES = tuple(f"{v.major}.{v.minor}" for v in SUPPORTED_VERSIONS)
_QUATERNION_TOLERANCE = 1e-3
_MATRIX_TOLERANCE = 1e-5


def rotation_matrix(rotation: Sequence[float]) -> np.ndarray:
    """A proper rotation matrix from 4 values (quaternion x, y, z, w; norm within 1e-3 of 1, then
    normalised) or 9 (row-major matrix, orthonormal within 1e-5, determinant +1); ValueError else."""
    r = np.asarray(rotation, dtype=float).ravel()
    if not np.all(np.isfinite(r)):
        raise ValueError(f"rotation has non-finite values: {list(r)}")
    if r.size == 4:
        norm = float(np.linalg.norm(r))
        if abs(norm - 1.0) > _QUATERNION_TOLERANCE:
            raise ValueError(f"quaternion norm {norm:.6g} is not 1 (within {_QUATERNION_TOLERANCE})")
        x, y, z, w = r / norm
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    if r.size == 9:
        m = r.reshape(3, 3)
        error = float(np.abs(m.T @ m - np.eye(3)).max())
        if error > _MATRIX_TOLERANCE or np.linalg.det(m) <= 0:
            raise ValueError(f"matrix is not a rotation (|R^T R - I| = {error:.3g}, "
                             f"det = {np.linalg.det(m):.6g})")
        return m.copy()
    raise ValueError(f"rotation needs 4 values (quaternion x, y, z, w) or 9 (row-major matrix), "
                     f"got {r.size}")


@dataclass(frozen=True)
class Calibration:
    """The pose of the mocap system's frame in ``arm_base``: ``p_arm = rotation @ p_mocap +
    translation``, rotation a proper rotation matrix, translation [m]."""

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self):
        rotation = rotation_matrix(np.asarray(self.rotation, dtype=float).ravel())
        translation = np.array(self.translation, dtype=float).reshape(-1)
        if translation.shape != (3,) or not np.all(np.isfinite(translation)):
            raise ValueError(f"translation must be three finite coordinates [m], got "
                             f"{self.translation!r}")
        rotation.setflags(write=False)
        translation.setflags(write=False)
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "translation", translation)

    @classmethod
    def identity(cls) -> "Calibration":
        return cls(np.eye(3), np.zeros(3))

    def to_arm(self, points) -> np.ndarray:
        """Points (n, 3) [m] in the mocap frame -> ``arm_base``."""
        return np.asarray(points, dtype=float) @ self.rotation.T + self.translation

    def to_mocap(self, points) -> np.ndarray:
        """Points (n, 3) [m] in ``arm_base`` -> the mocap frame (the inverse of :meth:`to_arm`)."""
        return (np.asarray(points, dtype=float) - self.translation) @ self.rotation


def _ipv4(value) -> Optional[ipaddress.IPv4Address]:
    if not isinstance(value, str):
        return None
    try:
        return ipaddress.IPv4Address(value)
    except (ipaddress.AddressValueError, ValueError, TypeError):
        return None


def _unicast(value) -> bool:
    address = _ipv4(value)
    return address is not None and not address.is_multicast


def _is_rotation(value) -> bool:
    try:
        rotation_matrix(value)
    except (ValueError, TypeError):
        return False
    return True


#: ``rig`` keys of the bridge (dotted, relative to ``rig``): kind, check, what is allowed.
MOCAP_SCHEMA = {
    "mocap.server_address": ("str", _unicast, "the IPv4 unicast address of the NatNet server "
                             "(Motive's computer; 127.0.0.1 for the emulator)"),
    "mocap.command_port": ("int", lambda v: 1 <= v <= 65535,
                           "the server's command port in [1, 65535] (Motive: 1510)"),
    "mocap.data_port": ("int", lambda v: 0 <= v <= 65535,
                        "a local UDP port in [0, 65535] for frames (Motive: 1511; 0: any free port)"),
    "mocap.local_address": ("str", _unicast, "an IPv4 address of this computer on the mocap "
                            "network (0.0.0.0: every interface)"),
    "mocap.multicast_group": ("str", lambda v: v == "" or (_ipv4(v) is not None and _ipv4(v).is_multicast),
                              "empty (unicast) or an IPv4 multicast group (Motive: 239.255.42.99)"),
    "mocap.multicast_interface": ("str", lambda v: v == "" or _unicast(v),
                                  "empty (local_address) or the IPv4 address of the interface that "
                                  "joins the group"),
    "mocap.natnet_version": ("str", lambda v: v == "" or v in VERSION_NAMES,
                             f"empty (the server's) or one of {', '.join(VERSION_NAMES)}, as a "
                             f"quoted string"),
    "mocap.keepalive_period": ("float", lambda v: 0 < v <= 60, "a period in (0, 60] s"),
    "mocap.timeout": ("float", lambda v: 0 < v <= 60,
                      "a time in (0, 60] s without an answer or a frame before reconnecting"),
    # at least four of the clock map's largest transport delays: a bridge stall shorter than the
    # window keeps its minimum, so that the frames queued behind it are not stamped as new
    "mocap.clock_window": ("float", lambda v: 4 * MAX_DELAY <= v <= 3600,
                           f"a window in [{4 * MAX_DELAY:g}, 3600] s (four of the largest transport "
                           f"delay, {MAX_DELAY:g} s)"),
    "mocap.poll_budget": ("float", lambda v: 1e-4 <= v <= 1,
                          "a time in [0.0001, 1] s: the longest one poll reads and handles datagrams "
                          "before it hands its frames on (the rest wait for the next)"),
    "mocap.max_distance": ("float", lambda v: 0 < v <= 100,
                           "a distance in (0, 100] m from arm_base beyond which a marker is no "
                           "position (unseen, counted)"),
    "mocap.markers.source": ("str", lambda v: v in SOURCES, " or ".join(SOURCES)),
    "mocap.markers.ids": ("ints", lambda v: len(v) >= 1 and len(set(v)) == len(v)
                          and all(0 <= a <= 0x7FFFFFFF for a in v),
                          "one or more distinct ids in [0, 2^31), base to tip (rigid body ids, or "
                          "labelled marker ids: asset id << 16 | marker number)"),
    "mocap.calibration.translation": ("floats", lambda v: len(v) == 3 and all(abs(a) <= 100 for a in v),
                                      "three coordinates [m] within 100 m: the mocap origin in "
                                      "arm_base"),
    "mocap.calibration.rotation": ("floats", _is_rotation,
                                   f"a unit quaternion x, y, z, w (norm within {_QUATERNION_TOLERANCE}"
                                   f" of 1) or a row-major rotation matrix (9 values, orthonormal "
                                   f"within {_MATRIX_TOLERANCE})"),
}


_FIELDS = {"server_address": "server_address", "command_port": "command_port",
           "data_port": "data_port", "local_address": "local_address",
           "multicast_group": "multicast_group", "multicast_interface": "multicast_interface",
           "natnet_version": "natnet_version", "keepalive_period": "keepalive_period",
           "timeout": "timeout", "clock_window": "clock_window", "poll_budget": "poll_budget",
           "max_distance": "max_distance",
           "source": "markers.source",
           "ids": "markers.ids", "translation": "calibration.translation",
           "rotation": "calibration.rotation"}


@dataclass(frozen=True)
class BridgeConfig:
    """The bridge's settings (``rig.mocap`` of ``config/mocap.yaml``; the defaults here are Motive's
    ports and an identity calibration). Every field is checked against :data:`MOCAP_SCHEMA`; a bad
    one raises ConfigError naming ``rig.mocap.<key>``.

    ``natnet_version``: the stream version to request (``""``: keep the server's). ``ids``: base to
    tip. ``translation`` [m] and ``rotation`` (quaternion x, y, z, w or row-major matrix): the
    calibration, see :class:`Calibration`. Periods and windows in seconds.
    """

    server_address: str = "127.0.0.1"
    command_port: int = 1510
    data_port: int = 1511
    local_address: str = "127.0.0.1"
    multicast_group: str = ""
    multicast_interface: str = ""
    natnet_version: str = ""
    keepalive_period: float = 1.0
    timeout: float = 2.0
    clock_window: float = 2.0
    poll_budget: float = 0.002
    max_distance: float = 1.0
    source: str = "rigid_bodies"
    ids: tuple = (1, 2, 3, 4)
    translation: tuple = (0.0, 0.0, 0.0)
    rotation: tuple = (0.0, 0.0, 0.0, 1.0)

    def __post_init__(self):
        for name in ("ids", "translation", "rotation"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        for name, key in _FIELDS.items():
            value = getattr(self, name)
            _, check, allowed = MOCAP_SCHEMA[f"mocap.{key}"]
            try:
                ok = bool(check(value))
            except (TypeError, ValueError):
                ok = False
            if not ok:
                shown = list(value) if isinstance(value, tuple) else value
                raise ConfigError(f"{NAMESPACE}.mocap.{key} = {shown!r} is not valid: expected {allowed}")

    @cached_property
    def calibration(self) -> Calibration:
        return Calibration(rotation_matrix(self.rotation), self.translation)

    @property
    def requested_version(self) -> Optional[Version]:
        if not self.natnet_version:
            return None
        major, minor = self.natnet_version.split(".")
        return Version(int(major), int(minor))

    @property
    def multicast(self) -> bool:
        return bool(self.multicast_group)


def load_mocap_config(path: Optional[str] = None, overrides: Optional[Mapping] = None,
                      node: str = "/**") -> BridgeConfig:
    """``rig.mocap`` of a parameter file (default: the package's ``config/mocap.yaml``) with dotted
    overrides relative to ``rig`` (``{"mocap.command_port": 1510}``), validated. Other ``rig.*``
    entries (other drivers' parameters) are left alone."""
    return bridge_config(mocap_values(path, overrides, node))


def bridge_config(values: Mapping) -> BridgeConfig:
    """The configuration of validated ``rig`` values (:func:`mocap_values`)."""
    return BridgeConfig(**{name: values[f"mocap.{key}"] for name, key in _FIELDS.items()})


def mocap_values(path: Optional[str] = None, overrides: Optional[Mapping] = None, node: str = "/**") -> dict:
    """The validated values of :func:`load_mocap_config`, by dotted key relative to ``rig``."""
    path = path or os.path.join(default_config_dir(), "mocap.yaml")
    params = read_parameters(path, node)
    rig = params.get(NAMESPACE)
    if not isinstance(rig, dict) or not isinstance(rig.get("mocap"), dict):
        raise ConfigError(f"{path}: no '{NAMESPACE}.mocap' parameters under {node}.ros__parameters")
    try:
        tree = apply_overrides({"mocap": rig["mocap"]}, overrides, MOCAP_SCHEMA, NAMESPACE)
        return validate_tree(tree, MOCAP_SCHEMA, NAMESPACE)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def calibration_overrides(path: str) -> dict:
    """``rig.mocap.calibration`` of a parameter file (e.g. an arm file written by
    soft-arm-identify) as overrides for :func:`load_mocap_config`; empty if the file has none."""
    rig = read_parameters(path).get(NAMESPACE)
    mocap = rig.get("mocap") if isinstance(rig, dict) else None
    calibration = mocap.get("calibration") if isinstance(mocap, dict) else None
    if not isinstance(calibration, dict):
        return {}
    return {f"mocap.calibration.{key}": value for key, value in calibration.items()}
