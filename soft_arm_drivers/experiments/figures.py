"""Figures like the paper's, read back from a recorded bag (any run: simulator or rig).

``task_error.png``: the task error per coordinate and its norm against time, with the 5 mm and
10 mm bands and the window starts; ``actuation.png``: measured and reference tendon shortenings
(the actuation coordinates) of the task's tendons; ``tensions.png``: the commanded tensions.
The bag is read with the independent ``rosbags`` reader.
"""
from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402


def read_series(bag_dir: str, topics=None) -> dict:
    """Per topic (without leading slash; ``topics``: only these): lists of (header stamp [s] or None,
    message), bag order."""
    out = {}
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([Path(bag_dir)], default_typestore=typestore) as reader:
        connections = [c for c in reader.connections if topics is None or c.topic.lstrip("/") in topics]
        if not connections:
            return out
        for conn, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, conn.msgtype)
            header = getattr(msg, "header", None)
            t = header.stamp.sec + 1e-9 * header.stamp.nanosec if header is not None else None
            out.setdefault(conn.topic.lstrip("/"), []).append((t, msg))
    return out


def make_figures(bag_dir: str, task, out_dir: str) -> list:
    """Write the three PNGs for ``task`` (a TaskConfig) into out_dir; returns their paths."""
    series = read_series(bag_dir)
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    frames = series.get("mocap/markers", [])
    if frames:
        t = np.array([s for s, _ in frames])
        x = np.array([task.space.from_markers(_positions(m)) for _, m in frames])
        starts = np.cumsum([0.0] + [ph.window for ph in task.phases for _ in ph.sequence])[:-1]
        targets = [np.array(task.targets[k]) for ph in task.phases for k in ph.sequence]
        rel = t - t[0]
        index = np.clip(np.searchsorted(starts, rel, side="right") - 1, 0, len(targets) - 1)
        err = np.array([targets[i] for i in index]) - x
        fig, ax = plt.subplots(figsize=(10, 4))
        for j, label in enumerate(task.space.labels()):
            ax.plot(rel, 1e3 * err[:, j], lw=0.6, alpha=0.6, label=label)
        ax.plot(rel, 1e3 * np.linalg.norm(err, axis=1), "k", lw=1.0, label="norm")
        for band, style in ((5, ":"), (10, "--")):
            ax.axhline(band, color="grey", ls=style, lw=0.8)
            ax.axhline(-band, color="grey", ls=style, lw=0.8)
        for s in starts[1:]:
            ax.axvline(s, color="grey", lw=0.4, alpha=0.5)
        ax.set_ylim(-40, 40)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("task error [mm]")
        ax.set_title(f"{task.name}: task error (5 mm and 10 mm bands)")
        ax.legend(loc="upper right", fontsize=7, ncol=3)
        paths.append(save_figure(fig, out_dir, "task_error.png"))
    states = series.get("tendon/state", [])
    refs = series.get("tendon/reference", [])
    if states:
        ts = np.array([s for s, _ in states])
        s_meas = np.array([m.position for _, m in states])
        fig, ax = plt.subplots(figsize=(10, 4))
        for k in task.tendons:
            line, = ax.plot(ts - ts[0], 1e3 * s_meas[:, k], lw=0.8, label=f"tendon {k + 1}")
            if refs:
                tr = np.array([s for s, _ in refs])
                ax.step(tr - ts[0], 1e3 * np.array([m.position[k] for _, m in refs]), where="post",
                        color=line.get_color(), ls="--", lw=0.8)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("shortening [mm]")
        ax.set_title("actuation coordinates: measured (solid) and reference (dashed)")
        ax.legend(fontsize=7)
        paths.append(save_figure(fig, out_dir, "actuation.png"))
    commands = series.get("tendon/command", [])
    if commands:
        tc = np.array([s for s, _ in commands])
        u = np.array([m.effort for _, m in commands])
        fig, ax = plt.subplots(figsize=(10, 3))
        for k in range(u.shape[1]):
            ax.plot(tc - tc[0], u[:, k], lw=0.6, label=f"tendon {k + 1}")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("tension [N]")
        ax.set_title("pulling forces")
        ax.legend(fontsize=7)
        paths.append(save_figure(fig, out_dir, "tensions.png"))
    return paths


def _positions(pose_array) -> np.ndarray:
    return np.array([[p.position.x, p.position.y, p.position.z] for p in pose_array.poses])


def save_figure(fig, out_dir, name) -> str:
    """Lay out, write ``out_dir/name`` (PNG, 110 dpi) and close ``fig``; the path."""
    path = os.path.join(out_dir, name)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
