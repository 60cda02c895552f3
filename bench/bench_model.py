"""Benchmarks of the Variable-Strain model's performance. Prints a table, writes JSON.

    python bench/bench_model.py [--output bench/results/model.json] [--skip-elastica]
    python bench/bench_model.py --warm-up     # PyElastica's kernels into numba's cache, then exit

Measures, on one core:
- one evaluation of all dynamics terms (M, C qd, F_g, F_el/K_t, A with friction, L_c; D and K are
  constant) at 12/16/20/24 DOF (the paper arm with Legendre orders 1..4 on the tendon span), and
  of its kinematics alone (the frames and Jacobians);
- building the model (the discretisation: basis, quadrature, constant matrices) at each of them;
- one frame's visibility in the simulated mocap (plant.yaml's cameras, the arm's body blocking
  the lines of sight to its four markers);
- one step of the simulated rig as the simulator node takes it (sense, then step; its mocap frames
  at their rate), on the triangle's plant and on the strike's with the ball held and swinging;
- static equilibrium from rest to 5 N on tendons 1 and 3, and the static balance's tangent at it,
  each with the analytic tangent and with the finite-difference oracle (n + 1 evaluations, the
  solver's before), side by side in the same run;
- simulation real-time factor at 1 ms IMEX steps, 10 s with a tendon step; at 20 DOF also with the
  plant's rotors, and their term (the tendons' rate bias) alone;
- the two integrators at equal accuracy (20 DOF, the plant's rotors, a 5 N step): the largest tip
  error over 1.5 s against a fine reference (ROS2 at 0.125 ms) and the real-time factor, for the
  Euler step at 1 ms and ROS2 at 1 to 5 ms; the longest ROS2 step as accurate as the Euler step at
  1 ms, and its speed over it;
- peak memory of the model process (before the integrators' comparison, whose fine reference run
  the bench keeps, and before PyElastica is imported);
- the tip error against the exact tendon-load solution by Legendre order, with and without a division
  break at the tendon end;
- the same cone as a horizontal cantilever under gravity in PyElastica and in this model, side by
  side, both settled and both warm (compiled before timing; PyElastica's cold first run apart),
  PyElastica at its best settings (the fewest elements reaching this model's accuracy against a
  planar Kirchhoff BVP reference, each at its largest stable and converged time step): tip
  difference, each against the reference, speed ratio; and each code's transient against a run of
  its own at a fine step (this model at the plant's step and ROS2 at 1-20 ms): the speed ratio
  where this model is as accurate as PyElastica's best in both senses, and where PyElastica is as
  accurate in its transient as the plant's step.
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np
from timing import best_of, results_path, write_results

from soft_arm_model import (ArmData, build_model, load_arm_config, marker_positions, simulate,
                            solve_equilibrium, tip_frame)
from soft_arm_model import kernels, statics
from soft_arm_model.model import R_BASE
from soft_arm_model.references import kirchhoff_cantilever_tip, tendon_load_tip
from soft_arm_drivers.sim.plant_config import load_plant_config

ORDERS = {12: [1, 0], 16: [2, 0], 20: [3, 0], 24: [4, 0]}  # Legendre orders per division


def _model(dof):
    return build_model(load_arm_config(overrides={"discretisation.legendre_order": ORDERS[dof]}))


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
        rows[dof] = {"dynamics_terms_us": 1e6 * best_of(lambda: kernels.evaluate(*args)),
                     "points": int(m.X.size)}
        args3 = (*m.kernel_args, q, qd, 3, False, *d.kernel_args)
        rows[dof]["with_coriolis_matrix_us"] = 1e6 * best_of(lambda: kernels.evaluate(*args3))
        args0 = (*m.kernel_args, q, qd, 0, False, *d.kernel_args)      # the frames and Jacobians alone
        rows[dof]["kinematics_us"] = 1e6 * best_of(lambda: kernels.evaluate(*args0))
    return rows


def bench_build():
    """Time [ms] to build the model at each DOF (what an identification fit does per evaluation)."""
    return {dof: 1e3 * best_of(lambda: _model(dof), repeats=5, inner=10) for dof in ORDERS}


def bench_visibility() -> float:
    """Time [us] of one frame's visibility of the declared plant's markers at a bent pose."""
    from soft_arm_drivers.sim.occlusion import Occlusions
    from soft_arm_drivers.sim.plant_config import load_plant_config
    arm = load_arm_config()
    m = build_model(arm)
    d = ArmData(m)
    marker_positions(m, solve_equilibrium(m, [2.0, 0.0, 3.0, 0.0]).q, d)
    occlusions = Occlusions(load_plant_config(arm).occlusion, m.marker_X.size, 1 / 240, 0)
    return 1e6 * best_of(lambda: occlusions.of_arm(m, d), inner=1000)


def bench_rig_step(steps=2000) -> dict:
    """Time [us] of one step of the simulated rig as the simulator node and the harness take it
    (sense the state, then step it under held tensions: Python between the two compiled halves) on
    the declared plant: the triangle's rig, and the strike's with its ball held and swinging."""
    from soft_arm_drivers.sim.simulated_rig import SimulatedRig
    from soft_arm_experiments.harness import load_setup

    def rig_of(task):
        setup = load_setup(task)
        u = np.full(len(setup.arm.tendons), setup.control.tension_min)
        rig = SimulatedRig(build_model(setup.plant.plant_arm(setup.arm)), setup.plant, np.zeros(len(u)), u,
                           setup.task.payload, setup.task.pendulum)
        return rig, u

    def step_time(rig, u):
        def run():
            for _ in range(steps):
                rig.begin_step()
                rig.end_step(u)
        return 1e6 * best_of(run, repeats=5, inner=1) / steps

    out = {"no_pendulum_us": step_time(*rig_of("triangle"))}
    rig, u = rig_of("pendulum")
    out["ball_held_us"] = step_time(rig, u)
    rig.release_pendulum()
    out["ball_swinging_us"] = step_time(rig, u)
    return out


def _best_solve(solve, repeats=7):
    solve()
    best, eq = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        eq = solve()
        best = min(best, time.perf_counter() - t0)
    return best, eq


def bench_statics(dof):
    """Static equilibrium 0 -> 5 N on tendons 1 and 3, and the static balance's tangent at it:
    the analytic one (what the solver uses) beside the finite-difference oracle (n + 1
    evaluations, what it used before), each alone and in the whole solve, in the same run."""
    m = _model(dof)
    u = np.array([5.0, 0.0, 5.0, 0.0])
    best, eq = _best_solve(lambda: solve_equilibrium(m, u))
    oracle = statics._Problem(m, ArmData(m), True, oracle=True)
    best_fd, eq_fd = _best_solve(lambda: statics._solve(oracle, u, None, None, 1e-10, 25, 1.0 / 4096))
    analytic = statics._Problem(m, ArmData(m), True)
    jac_us = 1e6 * best_of(lambda: analytic.linearise(eq.q, u), inner=200)
    jac_fd_us = 1e6 * best_of(lambda: oracle.linearise(eq.q, u), inner=20)
    return {"dof": dof, "ms": 1e3 * best, "newton_iterations": eq.iterations,
            "load_steps": eq.load_steps, "tip_m": tip_frame(m, eq.q).p.tolist(),
            "finite_difference_ms": 1e3 * best_fd, "finite_difference_newton_iterations": eq_fd.iterations,
            "speed_ratio_solve": best_fd / best,
            "tip_difference_m": float(np.linalg.norm(tip_frame(m, eq.q).p - tip_frame(m, eq_fd.q).p)),
            "jacobian_us": jac_us, "finite_difference_jacobian_us": jac_fd_us,
            "speed_ratio_jacobian": jac_fd_us / jac_us}


def bench_simulation(dof, duration=10.0, rotor_mass=None, repeats=3):
    """10 s of a tension step at 1 ms steps, the best of ``repeats`` runs as every other figure here
    (one run on a shared two-core machine varies by a tenth and more from one minute to the next);
    ``rotor_mass`` [kg] per tendon as the plant has them (their term is the tendons' rate bias,
    :func:`kernels.tendon_rate_bias`), or none."""
    m = _model(dof)
    q0 = solve_equilibrium(m, np.zeros(4)).q
    step = np.array([5.0, 0.0, 5.0, 0.0])
    simulate(m, q0, np.zeros(m.n), lambda t: step, 0.01, rotor_mass=rotor_mass)
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        tr = simulate(m, q0, np.zeros(m.n), lambda t: step if t >= 1.0 else np.zeros(4), duration,
                      rotor_mass=rotor_mass)
        walls.append(time.perf_counter() - t0)
    wall = min(walls)
    return {"dof": dof, "dt_s": 1e-3, "simulated_s": duration, "wall_s": wall, "runs_wall_s": walls,
            "real_time_factor": duration / wall, "final_tip_m": tip_frame(m, tr.q[-1]).p.tolist(),
            "rotor_mass_kg": None if rotor_mass is None else list(rotor_mass)}


def bench_rotor_term(dof=20, repeats=20000):
    """The tendons' rate bias (dA0/dt)^T qd at a moving state [us]: the rotors' share of a step."""
    m = _model(dof)
    d = ArmData(m)
    q = solve_equilibrium(m, np.array([5.0, 0.0, 5.0, 0.0])).q
    qd = np.random.default_rng(0).normal(0.0, 0.3, m.n)
    kernels.evaluate(*m.kernel_args, q, qd, 1, False, *d.kernel_args)
    a, out = m.kernel_args, np.zeros(m.n_tendons)
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(repeats):
            kernels.tendon_rate_bias(a[0], a[1], d.xi, qd, a[12], a[13], a[15], out)
        best = min(best, (time.perf_counter() - t0) / repeats * 1e6)
    return best


def bench_convergence(u=(0.0, 0.0, 2.0, 0.0)):
    """Tip error against the exact tendon-load solution (no gravity) by Legendre order, with and
    without a division break at the tendon end."""
    rows = []
    for order in (1, 2, 3, 5):
        rows.append(_convergence_row([0.325, 0.38], [order, 0], u))
    for order in (3, 5, 7):
        rows.append(_convergence_row([0.38], [order], u))
    return rows


def _convergence_row(ends, orders, u):
    over = {"gravity": [0.0, 0.0, 0.0], "discretisation.division_ends": ends,
            "discretisation.legendre_order": orders,
            "discretisation.gauss_points": [o + 6 for o in orders],
            "discretisation.allow_tendon_end_inside_division": len(ends) == 1}
    m = build_model(load_arm_config(overrides=over))
    tip = tip_frame(m, solve_equilibrium(m, list(u), friction=False).q).p
    err = np.linalg.norm(tip - tendon_load_tip(m.config, list(u), R_BASE))
    return {"division_ends_m": ends, "legendre_order": orders, "dof": m.n, "tendons_n": list(u),
            "tip_error_m": float(err)}


SAMPLE_S = 0.02          # s: the cantilever's tips compared along the transient, every SAMPLE_S
OWN_STEPS = (("imex", 1e-3),) + tuple(("ros2", dt) for dt in (1e-3, 2e-3, 5e-3, 1e-2, 2e-2))  # dt <= SAMPLE_S
OWN_REFERENCE = ("ros2", 1.25e-4)
ELASTICA_FINE = 16       # PyElastica's own reference steps this many times shorter than its chosen step


def transient_error(track, reference) -> float:
    """The largest distance [m] between two tip tracks (k, 2) sampled at the same times, over the
    samples both have."""
    k = min(len(track), len(reference))
    return float(np.linalg.norm(np.asarray(track)[:k] - np.asarray(reference)[:k], axis=1).max())


def cheapest_at_accuracy(runs, transient, settled):
    """The fastest of ``runs`` (dicts with ``wall_s``, ``transient_error_m`` and
    ``error_vs_kirchhoff_m``) at least as accurate as (``transient``, ``settled``) [m] in both;
    None if none is."""
    accurate = [r for r in runs
                if r["transient_error_m"] <= transient and r["error_vs_kirchhoff_m"] <= settled]
    return min(accurate, key=lambda r: r["wall_s"], default=None)


def _cantilever_run(m, method, dt, duration, repeats=1) -> dict:
    """This model's cantilever released from straight: the best wall time [s] of ``repeats`` warm
    runs and the tip (x, y) [m] every :data:`SAMPLE_S` (the track) and at the end."""
    every = int(round(SAMPLE_S / dt))
    if abs(every * dt - SAMPLE_S) > 1e-12:
        raise ValueError(f"a step of {dt} s does not divide the sampling period {SAMPLE_S} s")
    simulate(m, np.zeros(m.n), np.zeros(m.n), lambda t: np.zeros(4), 0.01, dt=dt, method=method)
    wall = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        tr = simulate(m, np.zeros(m.n), np.zeros(m.n), lambda t: np.zeros(4), duration, dt=dt, method=method)
        wall = min(wall, time.perf_counter() - t0)
    track = np.array([(-p[2], p[0]) for p in (tip_frame(m, q).p for q in tr.q[::every])])
    tip = tip_frame(m, tr.q[-1]).p
    return {"wall_s": wall, "track": track, "tip": np.array([-tip[2], tip[0]])}


def bench_cantilever(duration=3.0, elastica=True):
    """Horizontal cantilever released from straight under gravity; both codes damped so that they
    settle within ``duration`` (this model: Kelvin-Voigt viscosity 30 kPa s; PyElastica: uniform
    velocity damping 10 1/s), both compared at the end with the Kirchhoff BVP. Both sides warm:
    this model's kernels are compiled by a short run first, PyElastica's by :func:`elastica_warm_up`
    (its cold first run, compilation included, reported apart). PyElastica at its best settings for
    this problem (:func:`elastica_settings`): the fewest elements that reach this model's accuracy
    against the Kirchhoff reference, each at the largest time step it is stable and converged with.

    Accuracy in two senses, each code against references of its own: the settled tip's error
    against the Kirchhoff tip (the space discretisation), and the transient's, the tip's largest
    distance along the run (every :data:`SAMPLE_S`) from the same code's run at a fine step (the
    time step: this model's ROS2 at 0.125 ms, PyElastica's chosen step / :data:`ELASTICA_FINE`), as
    the two codes' transients differ by their damping models, not by their accuracy. Ratios: the
    plant's step (Euler, 1 ms) against PyElastica's best (``speed_ratio_dynamics``); this model's
    fastest step (of :data:`OWN_STEPS`) as accurate as PyElastica's best in both senses against
    it (``speed_ratio_equal_accuracy``); PyElastica's largest step as accurate in its transient as
    the plant's step against that step (``speed_ratio_plant_step_accuracy``); the static solve
    against PyElastica's best (``speed_ratio_statics``)."""
    g_acc = 9.81
    m = build_model(load_arm_config(overrides={"gravity": [-g_acc, 0.0, 0.0],
                                               "material.viscosity": 3.0e4}))
    ref = kirchhoff_cantilever_tip(m.config, g_acc)
    out = {"duration_s": duration, "kirchhoff_tip_m": ref.tolist(), "sample_s": SAMPLE_S}
    own_reference = _cantilever_run(m, *OWN_REFERENCE, duration)["track"]
    own = []
    for method, dt in OWN_STEPS:
        run = _cantilever_run(m, method, dt, duration, repeats=3)
        own.append({"method": method, "dt_s": dt, "wall_s": run["wall_s"],
                    "transient_error_m": transient_error(run["track"], own_reference),
                    "error_vs_kirchhoff_m": float(np.linalg.norm(run["tip"] - ref)), "tip": run["tip"]})
    plant_step = own[0]
    wall, ours = plant_step["wall_s"], plant_step["tip"]
    solve_equilibrium(m, np.zeros(4))                                      # warm, as the runs are
    t0 = time.perf_counter()
    static_tip = tip_frame(m, solve_equilibrium(m, np.zeros(4)).q).p
    static_wall = time.perf_counter() - t0
    error = plant_step["error_vs_kirchhoff_m"]
    out["this_model"] = {"dof": m.n, "dt_s": 1e-3, "wall_s": wall, "real_time_factor": duration / wall,
                         "tip_m": ours.tolist(), "error_vs_kirchhoff_m": error,
                         "transient_error_m": plant_step["transient_error_m"],
                         "static_solve_ms": 1e3 * static_wall,
                         "static_error_vs_kirchhoff_m": float(np.linalg.norm(
                             np.array([-static_tip[2], static_tip[0]]) - ref))}
    out["this_model_steps"] = [{k: v for k, v in r.items() if k != "tip"} for r in own]
    if not elastica:
        return out
    cold_s = elastica_warm_up(m.config, g_acc)
    settings = elastica_settings(m.config, g_acc, duration, ref, error)
    n_el, dt = settings["elements"], settings["dt_s"]
    run = min((elastica_cantilever(m.config, g_acc, duration, n_el, dt, sample=SAMPLE_S) for _ in range(3)),
              key=lambda r: r["wall_s"])                            # best of three, as this model's
    fine = elastica_cantilever(m.config, g_acc, duration, n_el, dt / ELASTICA_FINE, sample=SAMPLE_S)["track"]
    transient = transient_error(run["track"], fine)
    pe_error = float(np.linalg.norm(run["tip"] - ref))
    out["pyelastica"] = {**settings, "wall_s": run["wall_s"], "real_time_factor": duration / run["wall_s"],
                         "tip_m": run["tip_m"], "error_vs_kirchhoff_m": pe_error,
                         "transient_error_m": transient, "fine_dt_s": dt / ELASTICA_FINE,
                         "cold_first_run_s": cold_s, "warmed": True}
    out["tip_difference_m"] = float(np.linalg.norm(run["tip"] - ours))
    out["speed_ratio_dynamics"] = run["wall_s"] / wall
    out["speed_ratio_statics"] = run["wall_s"] / static_wall
    equal = cheapest_at_accuracy(own, transient, pe_error)
    out["this_model_at_pyelastica_accuracy"] = None if equal is None else \
        {k: v for k, v in equal.items() if k != "tip"}
    out["speed_ratio_equal_accuracy"] = None if equal is None else run["wall_s"] / equal["wall_s"]
    out["pyelastica_at_plant_step_accuracy"] = None
    out["speed_ratio_plant_step_accuracy"] = None
    for step in sorted((s for s in ELASTICA_STEPS if dt / ELASTICA_FINE < s < dt), reverse=True):
        finer = elastica_cantilever(m.config, g_acc, duration, n_el, step, sample=SAMPLE_S)
        finer_error = transient_error(finer["track"], fine)
        if finer_error <= plant_step["transient_error_m"]:
            out["pyelastica_at_plant_step_accuracy"] = {
                "elements": n_el, "dt_s": step, "wall_s": finer["wall_s"], "transient_error_m": finer_error}
            out["speed_ratio_plant_step_accuracy"] = finer["wall_s"] / wall
            break
    return out


def _elastica_system(config, g_acc, n_elements, dt):
    """PyElastica's cantilever of the cone ``config``: (the system, the rod, its stepper)."""
    import elastica as ea

    class Sim(ea.BaseSystemCollection, ea.Constraints, ea.Forcing, ea.Damping):
        pass

    geo, mat = config.geometry, config.material
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
    sim.dampen(rod).using(ea.AnalyticalLinearDamper, uniform_damping_constant=10.0, time_step=dt)
    sim.finalize()
    return sim, rod, ea.PositionVerlet()


def elastica_cantilever(config, g_acc, duration, n_elements, dt, sample=None) -> dict:
    """One PyElastica run of ``duration`` [s]: the stepping's wall time [s] (the set-up left out),
    the settled tip (x, y) [m] and whether it stayed finite and within twice the rod's length; with
    ``sample`` [s] also the tip every ``sample`` from the start (the track; linear between the two
    steps about a sample time that is not a step's)."""
    sim, rod, stepper = _elastica_system(config, g_acc, n_elements, dt)
    track = [rod.position_collection[:2, -1].copy()]
    t0 = time.perf_counter()
    t = 0.0
    for i in range(1, int(round(duration / dt)) + 1):
        due = sample and i * dt >= len(track) * sample - 1e-12      # this step reaches a sample time
        if due:
            before = rod.position_collection[:2, -1].copy()
        t = stepper.step(sim, t, dt)
        if due:
            w = (len(track) * sample - (i - 1) * dt) / dt           # of the way through this step
            track.append(before + w * (rod.position_collection[:2, -1] - before))
    wall = time.perf_counter() - t0
    tip = rod.position_collection[:2, -1].copy()
    stable = bool(np.all(np.isfinite(rod.position_collection))
                  and np.abs(rod.position_collection).max() < 2.0 * config.geometry.length)
    return {"wall_s": wall, "tip": tip, "tip_m": tip.tolist(), "stable": stable, "track": np.array(track)}


def elastica_warm_up(config, g_acc) -> float:
    """Compile PyElastica's kernels (numba, cached or not) by a few steps; the wall time [s] of that
    first run, compilation included: what a cold cache adds to a first timing."""
    t0 = time.perf_counter()
    sim, _, stepper = _elastica_system(config, g_acc, 10, 1e-5)
    t = 0.0
    for _ in range(10):
        t = stepper.step(sim, t, 1e-5)
    return time.perf_counter() - t0


ELASTICA_ELEMENTS = (20, 40, 80, 160)
ELASTICA_STEPS = tuple(2e-5 * 2.0 ** k for k in range(8))        # 20 us .. 2.56 ms
CONVERGED = 1e-3         # m: a step whose settled tip is this close to the half step's is converged


def elastica_largest_step(config, g_acc, duration, n_elements) -> tuple:
    """(the largest step of :data:`ELASTICA_STEPS` [s] whose settled tip is within
    :data:`CONVERGED` of the tip with half that step, that run) for ``n_elements``; a step at which
    the rod leaves twice its length or goes NaN is unstable, one it stays bounded at but settles
    elsewhere than with half the step is not converged either (None: no step is)."""
    runs = {}

    def run(step):
        if step not in runs:
            runs[step] = elastica_cantilever(config, g_acc, duration, n_elements, step)
        return runs[step]

    for step in sorted(ELASTICA_STEPS, reverse=True)[:-1]:
        if not run(step)["stable"] or not run(step / 2.0)["stable"]:
            continue
        if np.linalg.norm(run(step)["tip"] - run(step / 2.0)["tip"]) <= CONVERGED:
            return step, run(step)
    return None, None


def elastica_settings(config, g_acc, duration, ref, target_error) -> dict:
    """PyElastica's best settings for the cantilever: for each element count of
    :data:`ELASTICA_ELEMENTS` in turn, its largest converged time step
    (:func:`elastica_largest_step`); the first count whose settled tip is within ``target_error``
    [m] of the Kirchhoff tip ``ref`` (this model's error: equal accuracy), else the most accurate
    tried. Call :func:`elastica_warm_up` first."""
    tried = []
    for n in ELASTICA_ELEMENTS:
        dt, run = elastica_largest_step(config, g_acc, duration, n)
        if dt is None:
            continue
        error = float(np.linalg.norm(run["tip"] - ref))
        tried.append({"elements": n, "dt_s": dt, "error_vs_kirchhoff_m": error})
        if error <= target_error:
            return {"elements": n, "dt_s": dt, "equal_accuracy": True, "tried": tried}
    best = min(tried, key=lambda r: r["error_vs_kirchhoff_m"])
    return {"elements": best["elements"], "dt_s": best["dt_s"], "equal_accuracy": False, "tried": tried}


INTEGRATOR_STEPS = {"imex": (1e-3,), "ros2": (1e-3, 2e-3, 4e-3, 5e-3)}


def bench_integrators(duration=1.5, sample=0.02):
    """The Euler step and ROS2 against a fine ROS2 reference (0.125 ms): largest tip error [m] over
    ``duration`` s of a 5 N step on tendons 1 and 3 at 0.2 s (sampled every ``sample`` s) and the
    real-time factor (best of three), 20 DOF, the plant's rotors."""
    m = _model(20)
    rotor = [load_plant_config(load_arm_config()).rotor_mass] * 4
    q0 = solve_equilibrium(m, np.zeros(4)).q
    step = np.array([5.0, 0.0, 5.0, 0.0])

    def run(method, dt):
        tr = simulate(m, q0, np.zeros(m.n), lambda t: step if t >= 0.2 else np.zeros(4), duration,
                      dt=dt, rotor_mass=rotor, method=method)
        return np.array([tip_frame(m, q).p for q in tr.q[::int(round(sample / dt))]])

    reference = run("ros2", 1.25e-4)
    rows = []
    for method, steps in INTEGRATOR_STEPS.items():
        for dt in steps:
            error = float(np.linalg.norm(run(method, dt) - reference, axis=1).max())
            wall = best_of(lambda: run(method, dt), repeats=3, inner=1)
            rows.append({"method": method, "dt_s": dt, "max_tip_error_m": error,
                         "real_time_factor": duration / wall})
    euler = rows[0]
    equal = max((r for r in rows[1:] if r["max_tip_error_m"] <= euler["max_tip_error_m"]),
                key=lambda r: r["dt_s"], default=None)
    return {"rotor_mass_kg": rotor, "duration_s": duration, "reference": {"method": "ros2", "dt_s": 1.25e-4},
            "runs": rows, "ros2_at_equal_accuracy": equal,
            "speed_ratio_at_equal_accuracy": None if equal is None else
            equal["real_time_factor"] / euler["real_time_factor"]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output", default=results_path("model.json"))
    ap.add_argument("--skip-elastica", action="store_true")
    ap.add_argument("--warm-up", action="store_true",
                    help="compile PyElastica's kernels into numba's cache and exit (CI's set-up does, as "
                         "soft-arm-warmup does the package's: the suite's bench test then loads them)")
    args = ap.parse_args(argv)
    if args.warm_up:
        print(f"PyElastica's kernels compiled or loaded in {elastica_warm_up(load_arm_config(), 9.81):.1f} s")
        return
    res = {}
    res["evaluation"] = bench_evaluation()
    res["build_ms"] = bench_build()
    res["mocap_visibility_us"] = bench_visibility()
    res["rig_step"] = bench_rig_step()
    res["statics"] = {dof: bench_statics(dof) for dof in (16, 20)}
    res["simulation"] = {dof: bench_simulation(dof) for dof in (16, 20)}
    rotor = load_plant_config(load_arm_config()).rotor_mass
    res["simulation_with_rotors"] = bench_simulation(20, rotor_mass=[rotor] * 4)
    res["rotor_term_us"] = bench_rotor_term()
    res["peak_memory_mb_model"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    res["integrators"] = bench_integrators()
    res["convergence"] = bench_convergence()
    res["cantilever"] = bench_cantilever(elastica=not args.skip_elastica)

    print("\nsoft_arm_model benchmarks (one core; targets in brackets)")
    print(f"{'DOF':>4} {'points':>6} {'dynamics terms [us] (<=50 @16)':>32} {'+ Coriolis matrix [us]':>24} "
          f"{'of which kinematics [us]':>26}")
    for dof, r in res["evaluation"].items():
        print(f"{dof:>4} {r['points']:>6} {r['dynamics_terms_us']:>32.1f} "
              f"{r['with_coriolis_matrix_us']:>24.1f} {r['kinematics_us']:>26.1f}")
    print("building the model [ms]: "
          + ", ".join(f"{dof} DOF {ms:.1f}" for dof, ms in res["build_ms"].items()))
    print(f"simulated mocap, one frame's visibility (self-occlusion): {res['mocap_visibility_us']:.1f} us")
    r = res["rig_step"]
    print(f"simulated rig, one step as the simulator node takes it: {r['no_pendulum_us']:.1f} us; the "
          f"strike's, its ball held {r['ball_held_us']:.1f} us, swinging {r['ball_swinging_us']:.1f} us")
    for dof, r in res["statics"].items():
        print(f"static equilibrium 0 -> 5 N on tendons 1 and 3, {dof} DOF: {r['ms']:.2f} ms "
              f"[<= 1.5 ms @20] ({r['newton_iterations']} Newton iterations, {r['load_steps']} load steps); "
              f"with the finite-difference tangent {r['finite_difference_ms']:.2f} ms "
              f"({r['finite_difference_newton_iterations']} iterations): {r['speed_ratio_solve']:.1f}x, "
              f"tips {1e9 * r['tip_difference_m']:.2g} nm apart")
        print(f"  static tangent dR/dq at it: analytic {r['jacobian_us']:.1f} us, finite differences "
              f"{r['finite_difference_jacobian_us']:.1f} us: {r['speed_ratio_jacobian']:.1f}x")
    for dof, r in res["simulation"].items():
        print(f"simulation 1 ms steps, 10 s, {dof} DOF: real-time factor {r['real_time_factor']:.1f} "
              + ("[>= 60] " if dof == 20 else "")
              + f"(best of {len(r['runs_wall_s'])}; the others "
              + ", ".join(f"{r['simulated_s'] / w:.1f}" for w in sorted(r['runs_wall_s'])[1:]) + ")")
    r = res["simulation_with_rotors"]
    print(f"  with the plant's rotors ({r['rotor_mass_kg'][0]:g} kg per tendon), 20 DOF: real-time factor "
          f"{r['real_time_factor']:.1f}; their term, the tendons' rate bias: {res['rotor_term_us']:.2f} us")
    r = res["integrators"]
    print("integrators, 20 DOF with the rotors, 1.5 s of a 5 N step, largest tip error against ROS2 at "
          "0.125 ms:")
    for row in r["runs"]:
        print(f"  {row['method']:>4} {row['dt_s'] * 1e3:4.1f} ms: {row['max_tip_error_m'] * 1e3:7.3f} mm, "
              f"real-time factor {row['real_time_factor']:5.1f}")
    if r["ros2_at_equal_accuracy"] is not None:
        print(f"  at the Euler step's accuracy ROS2 steps {r['ros2_at_equal_accuracy']['dt_s'] * 1e3:g} ms: "
              f"real-time factor {r['ros2_at_equal_accuracy']['real_time_factor']:.1f}, "
              f"{r['speed_ratio_at_equal_accuracy']:.2f}x the Euler step's [>= 60 with it]")
    print(f"peak memory of the model process: {res['peak_memory_mb_model']:.0f} MB [< 300 MB]")
    print("tip error against the exact tendon-load solution (2 N on tendon 3, no gravity):")
    for r in res["convergence"]:
        print(f"  divisions {r['division_ends_m']}, orders {r['legendre_order']} ({r['dof']} DOF): "
              f"{1e3 * r['tip_error_m']:.4f} mm")
    c = res["cantilever"]
    vm = c["this_model"]
    print(f"cantilever under gravity, {c['duration_s']} s, damped to settle: this model ({vm['dof']} DOF, "
          f"1 ms) {vm['wall_s']:.2f} s wall (RTF {vm['real_time_factor']:.1f}), tip error vs Kirchhoff "
          f"{1e3 * vm['error_vs_kirchhoff_m']:.2f} mm; static solve {vm['static_solve_ms']:.1f} ms, "
          f"error {1e3 * vm['static_error_vs_kirchhoff_m']:.2f} mm")
    if "pyelastica" in c:
        pe = c["pyelastica"]
        equal = "at equal accuracy" if pe["equal_accuracy"] else "its best accuracy, short of this model's"
        print(f"  PyElastica, warm ({pe['elements']} elements, dt {pe['dt_s']:g} s, the largest converged; "
              f"{equal}) {pe['wall_s']:.2f} s wall (RTF {pe['real_time_factor']:.2f}), tip error vs "
              f"Kirchhoff {1e3 * pe['error_vs_kirchhoff_m']:.2f} mm; tip difference "
              f"{1e3 * c['tip_difference_m']:.2f} mm; speed ratio {c['speed_ratio_dynamics']:.1f}x "
              f"(same simulated time), {c['speed_ratio_statics']:.0f}x (static solve); its cold first "
              f"run {pe['cold_first_run_s']:.2f} s (compilation)")
        for r in pe["tried"]:
            print(f"    {r['elements']:>3} elements: largest converged dt {r['dt_s']:g} s, tip error "
                  f"{1e3 * r['error_vs_kirchhoff_m']:.2f} mm")
        print(f"  transients, each against its own code at a fine step (largest tip distance, every "
              f"{1e3 * c['sample_s']:.0f} ms): PyElastica {1e3 * pe['transient_error_m']:.2f} mm; "
              "this model:")
        for r in c["this_model_steps"]:
            print(f"    {r['method']:>4} {r['dt_s'] * 1e3:4.0f} ms: transient "
                  f"{1e3 * r['transient_error_m']:7.3f} mm, settled vs Kirchhoff "
                  f"{1e3 * r['error_vs_kirchhoff_m']:.2f} mm, {1e3 * r['wall_s']:6.1f} ms wall")
        eq = c["this_model_at_pyelastica_accuracy"]
        if eq is not None:
            print(f"  as accurate as PyElastica's best in both: {eq['method']} at {eq['dt_s'] * 1e3:g} ms, "
                  f"{c['speed_ratio_equal_accuracy']:.0f}x [>= 300]")
        pp = c["pyelastica_at_plant_step_accuracy"]
        if pp is not None:
            print(f"  PyElastica as accurate in its transient as the plant's step: dt {pp['dt_s']:g} s, "
                  f"{pp['wall_s']:.2f} s wall, {c['speed_ratio_plant_step_accuracy']:.0f}x")
    write_results(args.output, res)


if __name__ == "__main__":
    main()
