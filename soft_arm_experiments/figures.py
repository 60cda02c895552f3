"""Figures like the paper's, read back from a recorded bag (any run: simulator or rig).

``task_error.png``: the task error per coordinate and its norm against time, with the 5 mm and
10 mm bands and the window starts; ``actuation.png``: measured and reference tendon shortenings
(the actuation coordinates) of the task's tendons; ``tensions.png``: the commanded tensions;
``strike.png`` (a task with a pendulum): the arm and the ball around the strike (Fig. 5);
``tracking.png`` (a task with track phases): desired and measured paths.
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

from soft_arm_drivers.recording.rosbag_writer import open_bag  # noqa: E402


def read_series(bag_dir: str, topics=None) -> dict:
    """Per topic (without leading slash; ``topics``: only these): lists of (header stamp [s] or None,
    message), bag order. A bag whose writer was cut off is recovered first
    (:func:`~soft_arm_drivers.recording.rosbag_writer.open_bag`); BagError for a directory that
    holds no bag."""
    open_bag(bag_dir)
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


def make_figures(bag_dir: str, task, out_dir: str, arm=None) -> list:
    """Write the PNGs for ``task`` (a TaskConfig) into out_dir (``strike.png`` too for a task with a
    pendulum, given its ``arm``, an ArmConfig); returns their paths."""
    series = read_series(bag_dir)
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    if task.pendulum is not None and arm is not None and series.get("pendulum/release"):
        paths.append(strike_figure(series, task, arm, out_dir))
    frames = series.get("mocap/markers", [])
    if frames:
        t = np.array([s for s, _ in frames])
        x = np.array([task.space.from_markers(_positions(m)) for _, m in frames])
        rel = t - t[0]
        starts, index, x_d = targets_at(task, rel)
        err = x_d - x
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
        windows = [(w, ph) for w, ph in enumerate(ph for ph in task.phases for _ in ph.sequence)
                   if ph.trajectory is not None]
        if windows:
            paths.append(tracking_figure(windows, index, x, x_d, task, out_dir))
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


def targets_at(task, rel) -> tuple:
    """The window starts [s], the window of each time ``rel`` [s] from the first frame, and the
    target [m] there (a track window's trajectory from its target)."""
    plan = [(ph, k) for ph in task.phases for k in ph.sequence]
    starts = np.cumsum([0.0] + [ph.window for ph, _ in plan])[:-1]
    index = np.clip(np.searchsorted(starts, rel, side="right") - 1, 0, len(plan) - 1)
    x_d = [plan[i][0].target_at(task.targets[plan[i][1]], r - starts[i]) for r, i in zip(rel, index)]
    return starts, index, np.array(x_d)


def tracking_figure(windows, index, x, x_d, task, out_dir: str) -> str:
    """``tracking.png``: for each track window, the desired path (dashed) and the measured one in
    the trajectory's plane [mm]."""
    fig, axes = plt.subplots(1, len(windows), figsize=(3.6 * len(windows), 3.8), squeeze=False)
    labels = task.space.labels()
    for ax, (w, ph) in zip(axes[0], windows):
        a, b = ph.trajectory.plane
        sel = index == w
        ax.plot(1e3 * x_d[sel, a], 1e3 * x_d[sel, b], "k--", lw=1.0, label="desired")
        ax.plot(1e3 * x[sel, a], 1e3 * x[sel, b], color="tab:red", lw=0.8, label="measured")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{labels[a]} [mm]")
        ax.set_ylabel(f"{labels[b]} [mm]")
        ax.set_title(f"{ph.name}: {ph.trajectory.shape}, {ph.trajectory.period:g} s", fontsize=9)
    axes[0][0].legend(fontsize=7)
    return save_figure(fig, out_dir, "tracking.png")


def strike_figure(series: dict, task, arm, out_dir: str) -> str:
    """``strike.png``, like the paper's Fig. 5: (A) the arm (base and markers) at instants from the
    release, the tip's and the ball's paths, side view; (B) the same paths seen from above with the
    ball's free swing (dashed), the target (circle) and the impact (crosses); all as the motion
    capture saw them, the impact from :func:`~.strike.measured_strike`."""
    from .strike import free_swing, measured_strike
    release = series["pendulum/release"][-1][1].stamp
    t_release = release.sec + 1e-9 * release.nanosec
    arm_frames = {s: _positions(m) for s, m in series.get("mocap/markers", []) if s >= t_release}
    balls = {s: m.pose.position for s, m in series.get("mocap/pendulum", []) if s >= t_release}
    stamps = sorted(set(arm_frames) & set(balls))
    markers = np.array([arm_frames[s] for s in stamps])
    ball = np.array([[balls[s].x, balls[s].y, balls[s].z] for s in stamps])
    rel = np.array(stamps) - t_release
    strike = measured_strike(task.pendulum, t_release, np.array(stamps), ball, markers, arm)
    impact = int(np.searchsorted(rel, strike["impact_time"])) if strike["struck"] else None
    tip = markers[:, -1]
    fig, (side, top) = plt.subplots(1, 2, figsize=(11, 5))
    for j, when in enumerate(np.linspace(0.0, min(rel[-1], 0.5), 6)):
        k = int(np.searchsorted(rel, when))
        chain = np.vstack([np.zeros(3), markers[min(k, len(rel) - 1)]])
        side.plot(chain[:, 1], chain[:, 2], "-o", ms=3, color=plt.cm.viridis(j / 5), lw=1.5,
                  label=f"arm at {rel[min(k, len(rel) - 1)]:.2f} s")
    nominal = free_swing(task.pendulum, rel)
    for ax, (a, b) in ((side, (1, 2)), (top, (0, 1))):
        ax.plot(tip[:, a], tip[:, b], color="tab:red", lw=1.0, label="tip")
        ax.plot(ball[:, a], ball[:, b], color="tab:blue", lw=1.0, label="ball")
        ax.plot(nominal[:, a], nominal[:, b], "k--", lw=0.8, label="ball, free swing")
        ax.plot(task.pendulum.lowest_point[a], task.pendulum.lowest_point[b], "o", mfc="none", ms=14,
                color="grey", label="target")
        if impact is not None:
            ax.plot(tip[impact, a], tip[impact, b], "x", color="tab:red", ms=10, mew=2)
            ax.plot(ball[impact, a], ball[impact, b], "x", color="tab:blue", ms=10, mew=2)
        ax.set_aspect("equal", adjustable="datalim")
    side.set_xlabel("y [m]")
    side.set_ylabel("z [m]")
    side.set_title("A: shapes from the release, side view")
    side.legend(fontsize=6, loc="lower left")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    outcome = (f"struck {strike['impact_time']:.3f} s after the release" if strike["struck"]
               else "missed")
    top.set_title(f"B: tip and ball from above ({outcome})")
    top.legend(fontsize=7)
    return save_figure(fig, out_dir, "strike.png")


def _positions(pose_array) -> np.ndarray:
    return np.array([[p.position.x, p.position.y, p.position.z] for p in pose_array.poses])


def save_figure(fig, out_dir, name) -> str:
    """Lay out, write ``out_dir/name`` (PNG, 110 dpi) and close ``fig``; the path."""
    path = os.path.join(out_dir, name)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
