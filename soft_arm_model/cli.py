"""``soft-arm-model``: inspect the arm model from the command line.

Subcommands: ``summary`` (DOF, modes, natural frequencies), ``equilibrium --tensions T1 .. Tn``
(tip pose and marker positions in arm_base, optional PNG of the shape), ``workspace`` (equilibria over
a tension grid, optional PNG). Every subcommand takes ``--config FILE``, repeated ``--set key=value``
overrides (dotted keys under ``arm``) and ``--json``.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from scipy.linalg import eig

from .config import load_arm_config
from .dynamics import DYNAMICS, KINEMATICS, evaluate, frame_at
from .model import ArmData, build_model
from .parameters import ConfigError
from .statics import EquilibriumError, solve_equilibrium
from .workspace import sample_workspace


def _overrides(pairs):
    out = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set expects key=value, got {pair!r}")
        out[key.strip()] = value.strip()
    return out


def _quaternion(R):
    """Unit quaternion [x, y, z, w] of a rotation matrix."""
    w = np.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.copysign(np.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return [float(x), float(y), float(z), float(w)]


def _natural_frequencies(model):
    """Undamped natural frequencies [Hz] about the unactuated equilibrium (hanging arm)."""
    eq = solve_equilibrium(model, np.zeros(model.n_tendons))
    M = evaluate(model, ArmData(model), eq.q, level=DYNAMICS).M
    lam = np.real(eig(eq.jacobian, M, right=False))
    return np.sort(np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi))


def _summary(model, args):
    cfg = model.config
    freqs = _natural_frequencies(model)
    out = {
        "dof": model.n,
        "modes": list(cfg.enabled_modes),
        "divisions_m": list(cfg.discretisation.division_ends),
        "legendre_order": list(cfg.discretisation.legendre_order),
        "points": int(model.X.size),
        "tendons": [t.name for t in cfg.tendons],
        "mass_kg": float(model.lumped_mass[:, 3].sum()),   # the tip mass included
        "natural_frequencies_hz": [float(f) for f in freqs],
    }
    if args.json:
        return out
    print(f"soft arm model: {out['dof']} DOF, modes {', '.join(out['modes'])}")
    print(f"  divisions end at {out['divisions_m']} m, Legendre orders {out['legendre_order']}, "
          f"{out['points']} points")
    print(f"  tendons: {', '.join(out['tendons'])}; mass {out['mass_kg']:.4f} kg")
    print("  natural frequencies [Hz]: " + ", ".join(f"{f:.3g}" for f in freqs))
    return None


def _shape_samples(model, q, count=80):
    return np.array([frame_at(model, q, X).p for X in np.linspace(0, model.length, count)])


def _save_3d_plot(model, path, title, draw):
    """A 3-D figure in arm_base scaled to the arm, drawn by ``draw(fig, ax)``, saved as PNG."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    draw(fig, ax)
    L = model.length
    ax.set(xlim=(-L, L), ylim=(-L, L), zlim=(-L, 0.1), xlabel="x [m]", ylabel="y [m]", zlabel="z [m]",
           title=title)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_shape(model, q, path, title):
    pts = _shape_samples(model, q)
    marks = evaluate(model, ArmData(model), q, level=KINEMATICS, markers=True).marker_p

    def draw(fig, ax):
        ax.plot(*pts.T, lw=3, color="tab:blue", label="backbone")
        ax.scatter(*marks.T, color="tab:red", label="markers")
        ax.legend()
    _save_3d_plot(model, path, title, draw)


def _equilibrium(model, args):
    u = np.array(args.tensions, dtype=float)
    if u.size != model.n_tendons:
        raise ConfigError(f"--tensions needs {model.n_tendons} values (one per tendon: "
                          f"{', '.join(model.tendon_names)}), got {u.size}")
    if np.any(u < 0):
        raise ConfigError("--tensions must be >= 0 N (tendons only pull)")
    eq = solve_equilibrium(model, u, friction=not args.no_friction)
    d = evaluate(model, ArmData(model), eq.q, level=KINEMATICS, markers=True)
    out = {"frame": "arm_base", "tensions_n": u.tolist(), "tip_position_m": d.p[-1].tolist(),
           "tip_rotation": d.R[-1].tolist(), "tip_quaternion_xyzw": _quaternion(d.R[-1]),
           "marker_positions_m": d.marker_p.tolist(), "q": eq.q.tolist(),
           "newton_iterations": eq.iterations, "residual": eq.residual}
    if args.plot:
        _plot_shape(model, eq.q, args.plot, f"tensions {u.tolist()} N")
        out["plot"] = args.plot
    if args.json:
        return out
    print(f"equilibrium for tensions {u.tolist()} N ({eq.iterations} Newton iterations)")
    print("  tip position [m] (arm_base): " + " ".join(f"{v:+.4f}" for v in d.p[-1]))
    print("  tip quaternion [x y z w]:    " + " ".join(f"{v:+.4f}" for v in out["tip_quaternion_xyzw"]))
    for X, p in zip(model.marker_X, d.marker_p):
        print(f"  marker at X = {X:.3f} m: " + " ".join(f"{v:+.4f}" for v in p))
    if args.plot:
        print(f"  shape plot: {args.plot}")
    return None


def _workspace(model, args):
    tendons = None if args.tendons is None else [k - 1 for k in args.tendons]
    ws = sample_workspace(model, args.levels, tendons=tendons, friction=not args.no_friction)
    out = {"frame": "arm_base", "levels_n": list(args.levels), "samples": int(ws.converged.size),
           "converged": int(ws.converged.sum()), "tensions_n": ws.tensions.tolist(),
           "tip_positions_m": [None if not ok else p.tolist() for p, ok in zip(ws.tip, ws.converged)]}
    if args.plot:
        def draw(fig, ax):
            sc = ax.scatter(*ws.tip[ws.converged].T, c=ws.tensions[ws.converged].sum(axis=1),
                            cmap="viridis", s=12)
            fig.colorbar(sc, ax=ax, shrink=0.6, label="total tension [N]")
        _save_3d_plot(model, args.plot, "tip workspace", draw)
        out["plot"] = args.plot
    if args.json:
        return out
    print(f"workspace: {out['converged']}/{out['samples']} equilibria over levels {out['levels_n']} N")
    tips = ws.tip[ws.converged]
    for axis, name in enumerate("xyz"):
        print(f"  tip {name} in [{tips[:, axis].min():+.3f}, {tips[:, axis].max():+.3f}] m")
    if args.plot:
        print(f"  plot: {args.plot}")
    return None


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--arm-file", "--config", dest="config", metavar="FILE",
                        help="arm description, e.g. an identified one (default: the package's "
                             "config/arm.yaml)")
    common.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="override a config value, e.g. --set material.youngs_modulus=2e5")
    common.add_argument("--json", action="store_true", help="machine-readable output (arm_base)")
    parser = argparse.ArgumentParser(prog="soft-arm-model", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("summary", parents=[common], help="DOF, modes, natural frequencies")
    p = sub.add_parser("equilibrium", parents=[common], help="static equilibrium for tensions")
    p.add_argument("--tensions", nargs="+", type=float, required=True, metavar="T",
                   help="tendon tensions [N], one per tendon (>= 0, pulling)")
    p.add_argument("--plot", metavar="PNG", help="write the shape to this PNG")
    p.add_argument("--no-friction", action="store_true", help="frictionless tendons")
    w = sub.add_parser("workspace", parents=[common], help="sample equilibria over a tension grid")
    w.add_argument("--levels", nargs="+", type=float, default=[0.0, 2.5, 5.0], metavar="T",
                   help="tension levels [N] per tendon (default 0 2.5 5)")
    w.add_argument("--tendons", nargs="+", type=int, metavar="K", help="tendons to vary (1-based)")
    w.add_argument("--plot", metavar="PNG", help="write the tip workspace to this PNG")
    w.add_argument("--no-friction", action="store_true", help="frictionless tendons")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        model = build_model(load_arm_config(args.config, _overrides(args.set)))
        handler = {"summary": _summary, "equilibrium": _equilibrium, "workspace": _workspace}
        out = handler[args.command](model, args)
    except (ConfigError, EquilibriumError, ValueError, OSError) as exc:
        print(f"soft-arm-model: error: {exc}", file=sys.stderr)
        return 2
    if out is not None:
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
