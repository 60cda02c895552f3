"""The figures of ``soft-arm-identify --plot DIR``: what the data said against what the identified
model predicts.

``markers.png``: every marker's coordinates per quasi-static sample, measured (registered into
arm_base) and predicted; ``shortenings.png``: the tendon shortenings per sample, measured (less the
identified encoder zero) and predicted; ``hysteresis.png``: per tendon, shortening against its
tension, loading and unloading (friction opens the loop); ``dynamics.png``: the tip's change in the
dynamic segments, measured and simulated with the identified viscosity and rotor mass.
"""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from soft_arm_model.identification import predict_samples  # noqa: E402

from .figures import save_figure  # noqa: E402


def identification_figures(result: dict, out_dir: str) -> list:
    """Write the figures of a fit (``result``: :func:`.identify_cli.identify`'s) into ``out_dir``;
    their paths."""
    os.makedirs(out_dir, exist_ok=True)
    static, samples = result["static"], result["samples"]
    predicted_p, predicted_s = predict_samples(static.arm, samples)
    measured_p = static.registration.to_arm(np.array([s.markers for s in samples]))
    measured_s = np.array([s.shortening for s in samples]) - static.encoder_zero
    tension = np.array([s.tension for s in samples])
    k = np.arange(1, len(samples) + 1)
    paths = []

    fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    for a, ax in enumerate(axes):
        for m in range(measured_p.shape[1]):
            line, = ax.plot(k, 1e3 * measured_p[:, m, a], "o", ms=3, label=f"marker {m + 1} measured")
            ax.plot(k, 1e3 * predicted_p[:, m, a], "-", lw=0.8, color=line.get_color(), label="predicted")
        ax.set_ylabel(f"{'xyz'[a]} [mm]")
    axes[0].legend(fontsize=6, ncol=4)
    axes[-1].set_xlabel("quasi-static sample")
    paths.append(save_figure(fig, out_dir, "markers.png"))

    fig, ax = plt.subplots(figsize=(10, 4))
    for j in range(measured_s.shape[1]):
        line, = ax.plot(k, 1e3 * measured_s[:, j], "o", ms=3, label=f"tendon {j + 1} measured")
        ax.plot(k, 1e3 * predicted_s[:, j], "-", lw=0.8, color=line.get_color())
    ax.set_xlabel("quasi-static sample")
    ax.set_ylabel("shortening [mm]")
    ax.legend(fontsize=7)
    paths.append(save_figure(fig, out_dir, "shortenings.png"))

    n_t = tension.shape[1]
    fig, axes = plt.subplots(1, n_t, figsize=(3 * n_t, 3), squeeze=False)
    for j, ax in enumerate(axes[0]):
        alone = np.all(np.delete(tension, j, axis=1) <= tension.min() + 1e-3, axis=1)
        order = np.flatnonzero(alone)
        ax.plot(tension[order, j], 1e3 * measured_s[order, j], "o-", ms=3, lw=0.6, label="measured")
        ax.plot(tension[order, j], 1e3 * predicted_s[order, j], "x--", ms=4, lw=0.6, label="predicted")
        ax.set_title(f"tendon {j + 1} alone", fontsize=9)
        ax.set_xlabel("tension [N]")
    axes[0][0].set_ylabel("shortening [mm]")
    axes[0][0].legend(fontsize=7)
    paths.append(save_figure(fig, out_dir, "hysteresis.png"))

    dynamic = result["dynamic"]
    if dynamic is not None:
        n = len(dynamic.segments)
        fig, axes = plt.subplots(n, 1, figsize=(10, 1.8 * n), squeeze=False)
        for data, (_, dp), ax in zip(dynamic.segments, dynamic.simulated, axes[:, 0]):
            for a in range(3):
                line, = ax.plot(data.t_m - data.t_start, 1e3 * data.dp[:, -1, a], lw=0.8,
                                label=f"tip {'xyz'[a]}")
                ax.plot(data.t_m - data.t_start, 1e3 * dp[:, -1, a], "--", lw=0.8, color=line.get_color())
            ax.set_ylabel("[mm]")
        axes[0, 0].legend(fontsize=7, ncol=3, title="measured (solid), simulated (dashed)", title_fontsize=7)
        axes[-1, 0].set_xlabel("time in segment [s]")
        paths.append(save_figure(fig, out_dir, "dynamics.png"))
    return paths
