"""Draw the documentation's diagrams into docs/_static/ (committed; rerun after changing them):

    python docs/make_figures.py

``graph.png``: the node graph on the simulator and on the rig; ``controller.png``: the two-level
controller. The other figures there come from the package's own tools: ``arm_shape.png`` from
``soft-arm-model equilibrium --tensions 2 0 1.5 0 --plot``, ``triangle_task_error.png`` from a
``soft-arm-experiment triangle`` run's ``figures/task_error.png``.
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
    _box(ax, 8.4, 3.4, "P-satI-D+\non thetabar_a(s)", w=2.4, h=1.0)
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


if __name__ == "__main__":
    STATIC.mkdir(exist_ok=True)
    graph()
    controller()
    print(f"wrote {STATIC / 'graph.png'} and {STATIC / 'controller.png'}")
