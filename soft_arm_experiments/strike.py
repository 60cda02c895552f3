"""The pendulum strike: when to send the reference and release the ball, and what happened.

**Timing.** The ball reaches its speed peak (the lowest point, the strike target) ``ball_time`` after
its release (the exact pendulum: :meth:`~soft_arm_control.pendulum_geometry.PendulumConfig.time_to_lowest`).
The arm needs ``arm_time`` from the reference step until its surface first touches a ball waiting at
that point: the move is *rehearsed* before anything moves, on the controller's model (its arm, its
``control.rotor_mass``, the inner loop as configured, no model error and no noise). With
``timing: rehearsed`` the reference goes out ``ball_time - arm_time`` after the release, or, when
the arm is the slower, the ball is released ``arm_time - ball_time`` after the reference (on the rig
that needs a release the runner triggers). With ``timing: planned`` (soft-arm-harness only) the
move is not a step but the fastest tension profile the model allows
(:mod:`soft_arm_control.strike_planner`): it passes through the target at speed rather than
arriving there, so it is timed for the centres to meet, the task point at the target at the plan's
duration as the ball reaches its lowest point, not for a first touch (which would be a glancing
blow at the ball's leading edge); it is still rehearsed, as a check that it gets there. With ``timing:
release`` both go at once (the paper's protocol). Either way the plan and the rehearsal's
prediction are reported.

**Metrics.** :func:`strike_metrics`, from the simulated rig's own record of the contact
(:class:`~soft_arm_drivers.sim.simulated_rig.StrikeRecord`): the impact time after the release, the
ball's speed just before and after the contact and its velocity change, the arm's speed at the
contact point; without an impact, the closest approach (smallest gap between the surfaces) and when
it happened. :func:`measured_strike`: the same, as far as the motion capture shows it (what the rig
can measure, and what the graph's task runner reports).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from soft_arm_control.actuation_map import actuation_map_for
from soft_arm_control.clik import ClikPoint
from soft_arm_control.outer_loop import outer_loop_for
from soft_arm_control.strike_planner import StrikeProfile
from soft_arm_control.two_level import TwoLevelController
from soft_arm_drivers.sim.pendulum import Pendulum, closest_capsule
from soft_arm_drivers.sim.simulated_rig import Plant, StrikeRecord
from soft_arm_model import build_model
from soft_arm_model.parameters import ConfigError


@dataclass(frozen=True)
class StrikePlan:
    """Delays [s] after the strike window's start of the reference step and of the release; the
    rehearsed time [s] from the step to the first touch of a ball at the lowest point (nan if the
    rehearsal never touches it) and the rehearsal's smallest gap to it [m]; the ball's time [s]
    from the release to the lowest point; the timing rule; the planned move (timing ``planned``;
    None otherwise)."""
    send_delay: float
    release_delay: float
    arm_time: float
    rehearsed_gap: float
    ball_time: float
    timing: str
    move: StrikeProfile | None = None

    @property
    def intercept_time(self) -> float:
        """The arm's time [s] from the step to the instant the timing puts at the ball's lowest
        point: the planned move's duration (its task point at the target), else ``arm_time``."""
        return self.arm_time if self.move is None else self.move.duration

    def as_dict(self) -> dict:
        out = {k: None if isinstance(v, float) and not np.isfinite(v) else v
               for k, v in {**vars(self), "intercept_time": self.intercept_time}.items()}
        out["move"] = None if self.move is None else self.move.as_dict()
        return out


REHEARSAL_STEP = 1e-3     # s, the rehearsal's time step (the plant's of plant.yaml)


def rehearse(model, control, task, actuation_map, goal: ClikPoint, duration: float,
             move: StrikeProfile | None = None, timestep: float = REHEARSAL_STEP) -> tuple[float, float]:
    """The strike's move from the hanging arm (the pretension on every tendon, where the harness
    starts), simulated on the controller's ``model`` for ``duration`` [s]: the precomputed goal
    ``goal`` (a ClikPoint) given at 0 through the task's outer loop (with its planned ``move``, if
    any, sampled at the CLIK rate from the start; the run samples it at the delivered mocap frames,
    up to a time step later) and the inner loop of ``control`` on the task's tendons through
    ``actuation_map``. Returns (time [s] of the first touch of the task's ball
    waiting at its lowest point, nan if none; the smallest surface gap to it [m])."""
    pendulum = task.pendulum
    plant = Plant(model, timestep, control.rotor_mass)
    plant.settle(np.full(model.n_tendons, control.tension_min))
    ctrl = TwoLevelController(model, control, task, actuation_map)
    ctrl.reference = ctrl.outer.goal(0.0, goal.x, "precomputed", goal, move=move)
    inner_every = max(1, int(round(1.0 / (control.inner_rate * timestep))))
    clik_every = max(1, int(round(1.0 / (control.clik_rate * timestep))))
    u, smallest = np.full(model.n_tendons, control.tension_min), np.inf
    for k in range(int(round(duration / timestep))):
        t = k * timestep
        plant.sense(markers=True)
        gap = plant.surface().closest(pendulum.lowest_point)[3] - pendulum.ball_radius
        smallest = min(smallest, gap)
        if gap <= 0.0:
            return t, smallest
        if k % clik_every == 0 and k:
            ref = ctrl.outer.frame(t, goal.x)
            if ref is not None:
                ctrl.reference = ref
        if k % inner_every == 0:
            s, sd = plant.tendons()
            u = ctrl.inner(t, s, sd)
        plant.step(u)
    return float("nan"), smallest


PLANNED_ON_THE_GRAPH = (
    "the graph does not run a planned strike (tasks.<task>.pendulum.timing: planned): the planned "
    "move passes the target at speed and must start within a few milliseconds of its plan, while the "
    "graph times goals by mocap frames, 5-10 ms late; run it in soft-arm-harness, or use timing "
    "rehearsed or release")


def strike_plan_for(arm, control, task) -> StrikePlan:
    """The plan of ``task``'s strike (its first window) as the graph's task runner makes it before
    anything moves: the target precomputed on the controller's model, the step rehearsed. A
    planned strike raises ConfigError (:data:`PLANNED_ON_THE_GRAPH`)."""
    if task.strike_timing == "planned":
        raise ConfigError(PLANNED_ON_THE_GRAPH)
    model = build_model(arm)
    outer = outer_loop_for(model, control, task)
    first = task.phases[0]
    goal = outer.precompute(np.array(task.targets[first.sequence[0]]))
    arm_time, gap = rehearse(model, control, task, actuation_map_for(model, control), goal, first.window)
    return plan_strike(task, arm_time, gap, 1.0 / control.inner_rate)


def plan_strike(task, arm_time: float, rehearsed_gap: float, period: float,
                move: StrikeProfile | None = None) -> StrikePlan:
    """When to step the reference (and start the planned ``move``) and release the ball (delays
    after the window's start), from the rehearsal's ``arm_time`` [s] (nan: it never touched) or
    the planned ``move``'s duration, and the task's timing rule; the delays are whole multiples of
    ``period`` [s] (the inner loop's, so that the move starts at an inner-loop update, as in the
    rehearsal)."""
    plan = StrikePlan(0.0, 0.0, arm_time, rehearsed_gap, task.pendulum.time_to_lowest(),
                      task.strike_timing, move)
    timed = task.strike_timing in ("rehearsed", "planned") and np.isfinite(plan.intercept_time)
    lead = round((plan.ball_time - plan.intercept_time if timed else 0.0) / period) * period
    return replace(plan, send_delay=max(lead, 0.0), release_delay=max(-lead, 0.0))


def strike_metrics(record: StrikeRecord, timestep: float) -> dict:
    """What the simulated contact did (JSON-ready, SI units): ``struck``; with an impact its time
    after the release [s], the ball's speed before and after [m/s] and velocity change [m/s,
    arm_base], the arm's speed at the contact point [m/s], the contact's duration [s] and deepest
    overlap [m]; without, the closest approach (smallest surface gap [m]) and its time after the
    release [s]."""
    out = {"struck": False}
    if record.release_time is None or not record.t:
        return out
    t = np.asarray(record.t) - record.release_time
    force = np.linalg.norm(np.asarray(record.force), axis=1)
    gap = np.asarray(record.gap)
    v = np.asarray(record.ball_velocity)
    touching = force > 0
    if not touching.any():
        k = int(np.argmin(gap))
        out.update(closest_approach=float(gap[k]), closest_time=float(t[k]))
        return out
    first = int(np.argmax(touching))
    after = first + int(np.argmin(touching[first:])) if not touching[first:].all() else len(t) - 1
    before = v[first - 1] if first > 0 else np.zeros(3)
    out.update(struck=True, impact_time=float(t[first]),
               contact_duration=float((after - first) * timestep),
               ball_speed_before=float(np.linalg.norm(before)),
               ball_speed_after=float(np.linalg.norm(v[after])),
               ball_velocity_change=(v[after] - before).tolist(),
               arm_speed=float(record.arm_speed[first]), deepest_overlap=float(-gap[first:after + 1].min()))
    return out


DEVIATION = 0.003        # m: a ball this far off its free swing has been struck (mocap noise ~0.2 mm)
SPEED_WINDOW = 0.02      # s of frames the ball's speeds are measured over, before and after


def free_swing(pendulum, times) -> np.ndarray:
    """The ball's centre [m] at ``times`` [s] after its release (ascending, >= 0) on a free swing."""
    ball = Pendulum(pendulum, youngs_modulus=0.0)           # no arm: the modulus is not used
    ball.release()
    out, t, step = [], 0.0, 2e-4
    for target in times:
        while t < target - 1e-12:
            h = min(step, target - t)
            ball.advance(h)
            t += h
        out.append(ball.p.copy())
    return np.array(out)


BACKBONE_SAMPLES = 40    # points of the backbone the markers are interpolated to


def marker_backbone(arm, markers) -> tuple[np.ndarray, np.ndarray]:
    """The backbone as the markers (n_markers, 3) [m] of ``arm`` (an ArmConfig) show it: a cubic
    spline in arc length through the base (arm_base's origin, leaving it along -z, clamped) and the
    markers, with no curvature at the free tip; (points (BACKBONE_SAMPLES, 3) [m], the cone's
    radius at each [m])."""
    import scipy.interpolate   # here: at import, 0.15 s of a task runner node's start

    g = arm.geometry
    X = np.concatenate([[0.0], arm.marker_positions])
    spline = scipy.interpolate.CubicSpline(X, np.vstack([np.zeros(3), markers]),
                                           bc_type=((1, np.array([0.0, 0.0, -1.0])), (2, np.zeros(3))))
    fine = np.linspace(0.0, X[-1], BACKBONE_SAMPLES)
    return spline(fine), g.base_radius + (g.tip_radius - g.base_radius) * fine / g.length


def measured_strike(pendulum, release_time: float, t, ball, markers, arm) -> dict:
    """The strike as the motion capture sees it (what the rig can measure): mocap frame times t
    [s], the ball marker (N, 3) and the arm's markers (N, n_markers, 3) [m] of ``arm`` (an
    ArmConfig: where the markers sit and the cone's radii); frames with an unseen marker are left
    out. The ball is
    struck at the last frame still within a third of :data:`DEVIATION` of its free swing
    before it leaves it by more (``impact_time`` after the release); its speeds before and after are
    fitted over :data:`SPEED_WINDOW` of frames on each side. Without an impact: the closest
    approach of the ball's surface to the arm's (:func:`marker_backbone`) and when."""
    t = np.asarray(t, dtype=float) - release_time
    ball, markers = np.asarray(ball, dtype=float), np.asarray(markers, dtype=float)
    seen = np.all(np.isfinite(ball), axis=1) & np.all(np.isfinite(markers), axis=(1, 2))
    keep = (t >= 0) & seen                       # the frames that saw the ball and every marker
    t, ball, markers = t[keep], ball[keep], markers[keep]
    out = {"struck": False}
    if t.size < 3:
        return out
    deviation = np.linalg.norm(ball - free_swing(pendulum, t), axis=1)
    off = deviation > DEVIATION
    if not off.any():
        gap = np.array([closest_capsule(*marker_backbone(arm, m), b)[3]
                        for m, b in zip(markers, ball)]) - pendulum.ball_radius
        k = int(np.argmin(gap))
        out.update(closest_approach=float(gap[k]), closest_time=float(t[k]))
        return out
    first = int(np.argmax(off))
    still = np.flatnonzero(deviation[:first] <= DEVIATION / 3)   # on the free swing, noise aside
    k = int(still[-1]) if still.size else 0

    def velocity(sel):
        if sel.sum() < 2:
            return None
        return np.polyfit(t[sel], ball[sel], 1)[0]
    before = velocity((t <= t[k]) & (t > t[k] - SPEED_WINDOW))
    after_start = t[k] + 2 * SPEED_WINDOW          # the contact lasts ~10 ms: skip it
    after = velocity((t >= after_start) & (t < after_start + SPEED_WINDOW))
    out.update(struck=True, impact_time=float(t[k]),
               ball_speed_before=None if before is None else float(np.linalg.norm(before)),
               ball_speed_after=None if after is None else float(np.linalg.norm(after)),
               ball_velocity_change=None if before is None or after is None else (after - before).tolist())
    return out


def format_strike(strike: dict) -> str:
    """A strike's plan and outcome (``plan``; ``simulated``, the contact's, where the simulator's
    own record is at hand; ``measured``, the motion capture's) as a few lines of text."""
    plan = strike["plan"]
    arm = ("never touches it" if plan["arm_time"] is None
           else f"touches it {plan['arm_time']:.3f} s after its step")
    if plan["move"] is not None:
        arm += f", the planned move passes the target {plan['move']['duration']:.3f} s after it starts"
    lines = ["Strike (paper: struck 0.35 s after the release, peak tip speed 4.37 m/s)",
             f"  plan ({plan['timing']}): the ball reaches its lowest point {plan['ball_time']:.3f} s after "
             f"the release; the rehearsed arm {arm}; reference at +{plan['send_delay']:.3f} s, release "
             f"at +{plan['release_delay']:.3f} s"]
    for source in ("simulated", "measured"):
        outcome = strike.get(source)
        if outcome is None:
            continue
        if outcome["struck"]:
            speeds = "" if outcome.get("ball_speed_after") is None else (
                f": ball {outcome['ball_speed_before']:.2f} -> {outcome['ball_speed_after']:.2f} m/s")
            contact = "" if "arm_speed" not in outcome else (
                f", arm {outcome['arm_speed']:.2f} m/s at the contact, "
                f"{outcome['contact_duration'] * 1e3:.0f} ms of contact, "
                f"{outcome['deepest_overlap'] * 1e3:.1f} mm deep")
            lines.append(f"  {source}: struck {outcome['impact_time']:.3f} s after the release"
                         f"{speeds}{contact}")
        elif "closest_approach" in outcome:
            lines.append(f"  {source}: missed, closest approach {outcome['closest_approach'] * 1e3:.1f} mm, "
                         f"{outcome['closest_time']:.3f} s after the release")
        else:
            lines.append(f"  {source}: the ball was never released")
    return "\n".join(lines)
