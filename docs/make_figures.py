"""Draw the documentation's diagrams into docs/_static/ (committed; rerun after changing them):

    python docs/make_figures.py

``graph.png``: the node graph on the simulator and on the rig; ``controller.png``: the two-level
controller; ``live_view.png``: the live view's scene 9 s into a triangle run in the harness (the
scene message itself, decoded as the Foxglove app decodes it and drawn here with matplotlib: the
tube, the markers seen, the estimate with the tip's ellipsoid, the target). The other figures
there come from the package's own tools: ``arm_shape.png`` from ``soft-arm-model equilibrium
--tensions 2 0 1.5 0 --plot``, ``triangle_task_error.png`` from a ``soft-arm-experiment triangle``
run's ``figures/task_error.png``.
"""
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

STATIC = Path(__file__).resolve().parent / "_static"


def _box(ax, x, y, text, w=2.2, h=0.8, color="#dbe9f6"):
    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle="round,pad=0.05",
                                facecolor=color, edgecolor="#34495e"))
    ax.text(x, y, text, ha="center", va="center", fontsize=9)


def _arrow(ax, a, b, label="", offset=(0.0, 0.15), style="-|>"):
    ax.add_patch(FancyArrowPatch(a, b, arrowstyle=style, mutation_scale=12, color="#34495e", lw=1.2))
    if label:
        ax.text((a[0] + b[0]) / 2 + offset[0], (a[1] + b[1]) / 2 + offset[1], label, ha="center",
                fontsize=7.5, color="#2c3e50")


def graph():
    fig, ax = plt.subplots(figsize=(10, 5.2))
    ax.set_xlim(0, 14)
    ax.set_ylim(0, 7.2)
    ax.axis("off")
    ax.add_patch(FancyBboxPatch((5.0, 0.45), 7.9, 2.05, boxstyle="round,pad=0.08", facecolor="#e3f4e3",
                                edgecolor="#5a9a5a", linestyle="--"))
    ax.text(8.95, 0.62, "on the simulator: the simulator node (VS model) in their place, publishing the "
            "same topics", ha="center", fontsize=7.5, color="#2e6b2e")
    _box(ax, 2.2, 6.2, "task_runner\n(goals, metrics)")
    _box(ax, 6.6, 6.2, "clik\n(outer loop, CLIK)")
    _box(ax, 11.3, 6.2, "inner_loop\n(P-satI-D+)")
    _box(ax, 6.6, 1.6, "mocap_bridge\n(NatNet)", color="#fde2c8")
    _box(ax, 11.3, 1.6, "motor_driver\n(CAN, MIT protocol)", color="#fde2c8")
    _box(ax, 2.2, 1.6, "recorder\n(MCAP bag)", color="#eeeeee")
    _arrow(ax, (3.3, 6.2), (5.5, 6.2), "task/goal")
    _arrow(ax, (7.7, 6.2), (10.2, 6.2), "tendon/reference")
    _arrow(ax, (11.7, 5.8), (11.7, 2.0), "tendon/command", offset=(0.85, 0.0))
    _arrow(ax, (10.9, 2.0), (10.9, 5.8), "tendon/state", offset=(-0.8, 0.0))
    _arrow(ax, (6.6, 2.0), (6.6, 5.8), "mocap/markers", offset=(-0.85, 0.0))
    _arrow(ax, (5.9, 2.0), (2.9, 5.8), "mocap/markers", offset=(-0.6, 0.0))
    ax.text(2.2, 0.95, "records every topic", ha="center", fontsize=7.5, color="#2c3e50")
    fig.tight_layout()
    fig.savefig(STATIC / "graph.png", dpi=120)
    plt.close(fig)


def controller():
    fig, ax = plt.subplots(figsize=(10, 3.6))
    ax.set_xlim(0, 14)
    ax.set_ylim(0, 5)
    ax.axis("off")
    _box(ax, 1.4, 3.4, "x_d\n(target)", w=1.6, color="#ffffff")
    _box(ax, 4.6, 3.4, "CLIK for\nunderactuated systems\n(precomputed, online)", w=2.8, h=1.2)
    _box(ax, 8.4, 3.4, "P-satI-D+\non shortenings s", w=2.4, h=1.0)
    _box(ax, 12.0, 3.4, "tendons, arm", w=2.0, color="#d5f0d5")
    _arrow(ax, (2.2, 3.4), (3.2, 3.4))
    _arrow(ax, (6.0, 3.4), (7.2, 3.4), "q_d: s_d, u_ff")
    _arrow(ax, (9.6, 3.4), (11.0, 3.4), "u (tensions)")
    _arrow(ax, (12.0, 2.9), (12.0, 1.6), style="-")
    _arrow(ax, (12.0, 1.6), (8.4, 1.6), "shortenings s, rates (500 Hz)", offset=(0.0, -0.35), style="-")
    _arrow(ax, (8.4, 1.6), (8.4, 2.9))
    _arrow(ax, (12.6, 2.9), (12.6, 0.6), style="-")
    _arrow(ax, (12.6, 0.6), (4.6, 0.6), "markers x (mocap, 240 Hz)", offset=(0.0, -0.35), style="-")
    _arrow(ax, (4.6, 0.6), (4.6, 2.8))
    fig.tight_layout()
    fig.savefig(STATIC / "controller.png", dpi=120)
    plt.close(fig)


def live_view(at: float = 9.0):
    import numpy as np
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    from soft_arm_experiments.harness import load_setup, run_experiment
    from soft_arm_experiments.live_view import LiveView

    setup = load_setup("triangle", overrides=["tasks.triangle.phases=[approach]",
                                              "tasks.triangle.phase.approach.window=5.0"], feedback="fused")
    view = LiveView(setup.arm.geometry.base_radius, setup.arm.geometry.tip_radius, trail=2.0)
    taken = []

    def observe(t, rig, frame, estimate, x_d, reference):
        if taken:
            return
        view.take_backbone(t, rig.plant.stepper.data.p)
        view.take_mocap(t, frame.markers)
        if estimate is not None:
            view.take_estimate(t, estimate.markers, estimate.marker_covariance[-1])
        view.take_target(setup.task.space.labels(), x_d)
        if t >= at:
            taken.append(view.scene().encode())

    run_experiment(setup, observer=observe)
    schema = __import__("foxglove").messages.SceneUpdate.get_schema()
    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(f)
    scene = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name)).FromString(taken[0])
    entities = {e.id: e for e in scene.entities}

    def at_pose(p):
        return np.array([p.position.x, p.position.y, p.position.z])

    def rotate(q, v):
        u, w = np.array([q.x, q.y, q.z]), q.w
        return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)

    fig = plt.figure(figsize=(6.4, 6.4))
    ax = fig.add_subplot(projection="3d")
    for c in entities["arm"].cylinders:
        half = rotate(c.pose.orientation, np.array([0.0, 0.0, 0.5 * c.size.z]))
        a, b = at_pose(c.pose) - half, at_pose(c.pose) + half
        ax.plot(*np.stack([a, b]).T, color="#e6801a", lw=400 * c.size.x * c.top_scale,
                solid_capstyle="round")
    seen = np.array([at_pose(s.pose) for s in entities["mocap"].spheres]).reshape(-1, 3)
    ax.scatter(*seen.T, color="#33e633", s=40, label="markers the mocap sees", depthshade=False)
    spheres = entities["estimate"].spheres
    estimated = np.array([at_pose(s.pose) for s in spheres[:-1]]).reshape(-1, 3)
    ax.scatter(*estimated.T, color="#1a99e6", s=18, label="the estimate's markers", depthshade=False)
    e = spheres[-1]
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.linspace(0, np.pi, 12))
    unit = np.stack([np.cos(u) * np.sin(v) * e.size.x, np.sin(u) * np.sin(v) * e.size.y,
                     np.cos(v) * e.size.z], axis=-1) / 2
    points = np.array([rotate(e.pose.orientation, p) for p in unit.reshape(-1, 3)]) + at_pose(e.pose)
    points = points.reshape(unit.shape)
    ax.plot_wireframe(points[..., 0], points[..., 1], points[..., 2], color="#1a99e6", lw=0.3,
                      label="the tip's one-sigma ellipsoid")
    target = np.array([at_pose(s.pose) for s in entities["target"].spheres]).reshape(-1, 3)
    ax.scatter(*target.T, color="#e61a1a", marker="x", s=60, label="target", depthshade=False)
    ax.set_xlim(-0.1, 0.15)
    ax.set_ylim(-0.05, 0.2)
    ax.set_zlim(-0.35, 0.0)
    ax.view_init(elev=15, azim=-60)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(f"the live view's scene, {at:.0f} s into the triangle (arm_base)", fontsize=10)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(STATIC / "live_view.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    STATIC.mkdir(exist_ok=True)
    graph()
    controller()
    live_view()
    print(f"wrote {STATIC / 'graph.png'}, {STATIC / 'controller.png'} and {STATIC / 'live_view.png'}")
