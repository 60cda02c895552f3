"""Benchmarks of the Variable-Strain model (issue: model performance). Prints a table, writes JSON.

    python bench/bench_model.py [--output bench/results/model.json] [--skip-elastica]

Measures, on one core:
- one evaluation of all dynamics terms (M, C qd, F_g, F_el/K_t, A with friction, L_c; D and K are
  constant) at 12/16/20/24 DOF (the paper arm with Legendre orders 1..4 on the tendon span);
- static equilibrium from rest to 5 N on tendons 1 and 3;
- simulation real-time factor at 1 ms IMEX steps, 10 s with a tendon step;
- peak memory of the model process (before PyElastica is imported);
- the same cone as a horizontal cantilever under gravity in PyElastica and in this model, side by
  side: tip difference, each against a planar Kirchhoff BVP reference, and the speed ratio.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time

import numpy as np

from soft_arm_model import ArmData, build_model, load_arm_config, simulate, solve_equilibrium, tip_frame
from soft_arm_model import kernels

ORDERS = {12: [1, 0], 16: [2, 0], 20: [3, 0], 24: [4, 0]}


def _model(dof, **extra):
    over = {"discretisation.legendre_order": ORDERS[dof]}
    over.update(extra)
    return build_model(load_arm_config(overrides=over))


def _best_of(fn, repeats=7, inner=500):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        best = min(best, (time.perf_counter() - t0) / inner)
    return best


def bench_evaluation():
    rows = {}
    rng = np.random.default_rng(0)
    for dof in ORDERS:
        m = _model(dof)
        d = ArmData(m)
        q = solve_equilibrium(m, [2.0, 0, 3.0, 0]).q
        qd = rng.normal(size=m.n) * 0.5
        args = (*m.kernel_args, q, qd, 2, False, *d.kernel_args)
        kernels.evaluate(*args)
        rows[dof] = {"dynamics_terms_us": 1e6 * _best_of(lambda: kernels.evaluate(*args)),
                     "points": int(m.X.size)}
        args3 = (*m.kernel_args, q, qd, 3, False, *d.kernel_args)
        rows[dof]["with_coriolis_matrix_us"] = 1e6 * _best_of(lambda: kernels.evaluate(*args3))
    return rows


def bench_statics(dof):
    m = _model(dof)
    u = np.array([5.0, 0.0, 5.0, 0.0])
    solve_equilibrium(m, u)
    best, eq = np.inf, None
    for _ in range(7):
        t0 = time.perf_counter()
        eq = solve_equilibrium(m, u)
        best = min(best, time.perf_counter() - t0)
    return {"dof": dof, "ms": 1e3 * best, "newton_iterations": eq.iterations,
            "load_steps": eq.load_steps, "tip_m": tip_frame(m, eq.q).p.tolist()}


def bench_simulation(dof, duration=10.0):
    m = _model(dof)
    q0 = solve_equilibrium(m, np.zeros(4)).q
    step = np.array([5.0, 0.0, 5.0, 0.0])
    simulate(m, q0, np.zeros(m.n), lambda t: step, 0.01)
    t0 = time.perf_counter()
    tr = simulate(m, q0, np.zeros(m.n), lambda t: step if t >= 1.0 else np.zeros(4), duration)
    wall = time.perf_counter() - t0
    return {"dof": dof, "dt_s": 1e-3, "simulated_s": duration, "wall_s": wall,
            "real_time_factor": duration / wall, "final_tip_m": tip_frame(m, tr.q[-1]).p.tolist()}


def _kirchhoff_tip(cfg, g_acc):
    from scipy.integrate import solve_bvp
    geo, mat = cfg.geometry, cfg.material
    L, E, rho = geo.length, mat.youngs_modulus, mat.density
    slope = (geo.tip_radius - geo.base_radius) / L

    def radius(s):
        return geo.base_radius + slope * s

    def rhs(s, y, c):
        W = rho * g_acc * np.pi * (radius(L) ** 3 - radius(s) ** 3) / (3 * slope)
        return np.vstack([y[1] / (E * np.pi * radius(s) ** 4 / 4), c * W * np.cos(y[0]),
                          np.cos(y[0]), np.sin(y[0])])

    s = np.linspace(0, L, 400)
    y = np.zeros((4, s.size))
    y[2] = s
    for c in np.linspace(0.1, 1.0, 10):
        sol = solve_bvp(lambda s, y: rhs(s, y, c), lambda a, b: np.array([a[0], b[1], a[2], a[3]]),
                        s, y, tol=1e-10, max_nodes=200000)
        s, y = sol.x, sol.y
    return np.array([y[2, -1], y[3, -1]])  # (along the clamp axis, along gravity)


def bench_cantilever(duration=8.0, elastica=True, n_elements=40, elastica_dt=2e-5):
    """Horizontal cantilever released from straight under gravity, settled by damping."""
    g_acc = 9.81
    over = {"gravity": [-g_acc, 0.0, 0.0]}
    m = _model(20, **over)
    cfg = m.config
    ref = _kirchhoff_tip(cfg, g_acc)
    out = {"duration_s": duration, "kirchhoff_tip_m": ref.tolist()}
    simulate(m, np.zeros(m.n), np.zeros(m.n), lambda t: np.zeros(4), 0.01)
    t0 = time.perf_counter()
    tr = simulate(m, np.zeros(m.n), np.zeros(m.n), lambda t: np.zeros(4), duration)
    wall = time.perf_counter() - t0
    tip = tip_frame(m, tr.q[-1]).p
    ours = np.array([-tip[2], tip[0]])
    t0 = time.perf_counter()
    static_tip = tip_frame(m, solve_equilibrium(m, np.zeros(4)).q).p
    static_wall = time.perf_counter() - t0
    out["vs_model"] = {"dof": m.n, "dt_s": 1e-3, "wall_s": wall, "tip_m": ours.tolist(),
                       "error_vs_kirchhoff_m": float(np.linalg.norm(ours - ref)),
                       "static_solve_ms": 1e3 * static_wall,
                       "static_tip_error_vs_kirchhoff_m": float(np.linalg.norm(
                           np.array([-static_tip[2], static_tip[0]]) - ref))}
    if not elastica:
        return out
    import elastica as ea

    class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Forcing, ea.Damping):
        pass

    geo, mat = cfg.geometry, cfg.material
    L = geo.length
    s_mid = (np.arange(n_elements) + 0.5) / n_elements * L
    radius = geo.base_radius + (geo.tip_radius - geo.base_radius) * s_mid / L
    sim = Sim()
    rod = ea.CosseratRod.straight_rod(n_elements, np.zeros(3), np.array([1.0, 0, 0]),
                                      np.array([0, 0, 1.0]), L, radius, mat.density,
                                      youngs_modulus=mat.youngs_modulus,
                                      shear_modulus=mat.youngs_modulus / 3.0)
    sim.append(rod)
    sim.constrain(rod).using(ea.OneEndFixedBC, constrained_position_idx=(0,),
                             constrained_director_idx=(0,))
    sim.add_forcing_to(rod).using(ea.GravityForces, acc_gravity=np.array([0.0, -g_acc, 0.0]))
    sim.dampen(rod).using(ea.AnalyticalLinearDamper, translational_damping_constant=0.3,
                          rotational_damping_constant=1e-5, time_step=elastica_dt)
    sim.finalize()
    steps = int(round(duration / elastica_dt))
    t0 = time.perf_counter()
    ea.integrate(ea.PositionVerlet(), sim, duration, steps, progress_bar=False)
    e_wall = time.perf_counter() - t0
    e_tip = rod.position_collection[:, -1]
    e_tip = np.array([e_tip[0], e_tip[1]])
    out["pyelastica"] = {"elements": n_elements, "dt_s": elastica_dt, "wall_s": e_wall,
                         "tip_m": e_tip.tolist(),
                         "error_vs_kirchhoff_m": float(np.linalg.norm(e_tip - ref))}
    out["tip_difference_m"] = float(np.linalg.norm(e_tip - ours))
    out["speed_ratio_dynamics"] = e_wall / wall
    out["speed_ratio_statics"] = e_wall / static_wall
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output", default=os.path.join(os.path.dirname(__file__), "results", "model.json"))
    ap.add_argument("--skip-elastica", action="store_true")
    args = ap.parse_args(argv)
    res = {"machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                       "cpus": os.cpu_count()}}
    res["evaluation"] = bench_evaluation()
    res["statics"] = {dof: bench_statics(dof) for dof in (16, 20)}
    res["simulation"] = {dof: bench_simulation(dof) for dof in (16, 20)}
    res["peak_memory_mb_model"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    res["cantilever"] = bench_cantilever(elastica=not args.skip_elastica)

    print("\nsoft_arm_model benchmarks (one core; targets in brackets)")
    print(f"{'DOF':>4} {'points':>6} {'dynamics terms [us] (<=50 @16)':>32} {'+ Coriolis matrix [us]':>24}")
    for dof, r in res["evaluation"].items():
        print(f"{dof:>4} {r['points']:>6} {r['dynamics_terms_us']:>32.1f} {r['with_coriolis_matrix_us']:>24.1f}")
    for dof, r in res["statics"].items():
        print(f"static equilibrium 0 -> 5 N on tendons 1 and 3, {dof} DOF: {r['ms']:.1f} ms "
              f"[<= 20 ms] ({r['newton_iterations']} Newton iterations, {r['load_steps']} load steps)")
    for dof, r in res["simulation"].items():
        print(f"simulation 1 ms steps, 10 s, {dof} DOF: real-time factor {r['real_time_factor']:.1f} [>= 20]")
    print(f"peak memory of the model process: {res['peak_memory_mb_model']:.0f} MB [< 300 MB]")
    c = res["cantilever"]
    vm = c["vs_model"]
    print(f"cantilever under gravity, {c['duration_s']} s: this model ({vm['dof']} DOF, 1 ms) "
          f"{vm['wall_s']:.2f} s wall, tip error vs Kirchhoff {1e3 * vm['error_vs_kirchhoff_m']:.2f} mm; "
          f"static solve {vm['static_solve_ms']:.1f} ms, error {1e3 * vm['static_tip_error_vs_kirchhoff_m']:.3f} mm")
    if "pyelastica" in c:
        pe = c["pyelastica"]
        print(f"  PyElastica ({pe['elements']} elements, dt {pe['dt_s']:g} s) {pe['wall_s']:.2f} s wall, "
              f"tip error vs Kirchhoff {1e3 * pe['error_vs_kirchhoff_m']:.2f} mm; tip difference "
              f"{1e3 * c['tip_difference_m']:.2f} mm; speed ratio {c['speed_ratio_dynamics']:.0f}x "
              f"(dynamics), {c['speed_ratio_statics']:.0f}x (statics) [> 10x]")
    os.makedirs(os.path.dirname(os.path.abspath(args.output)), exist_ok=True)
    with open(args.output, "w", encoding="utf-8") as fh:
        json.dump(res, fh, indent=2)
    print(f"\nJSON: {args.output}")


if __name__ == "__main__":
    main()
