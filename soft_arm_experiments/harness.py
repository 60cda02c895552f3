"""The closed-loop harness (ROS-free): plant, sensors, the two-level controller and the paper's protocols.

- Plant: the Variable-Strain model with its own parameters (``plant.yaml``: scaled E and viscosity,
  its own friction), stepped by the IMEX integrator at ``plant.timestep``.
- Sensors: encoders (tendon shortening from the motor angle through the pulley, quantised, zeroed at
  start-up on the hanging arm and offset by the controller model's prediction of that pose) and
  motion capture (markers at ``mocap.rate``, Gaussian noise, delivered ``mocap.latency`` late).
- Controller: P-satI-D+ at ``control.inner_loop.rate`` on the measured shortenings; the CLIK
  precomputed (every target is solved before anything moves) then online at ``control.clik.rate``
  from ``control.clik.switch_delay`` after each target change, as in the paper's protocol; replay
  phases give the configurations stored at the end of the CLIK windows straight to the inner loop.

All times are simulated seconds on one clock; every rate is realised on the plant's time grid.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np

from soft_arm_control.actuation_map import ActuationMap
from soft_arm_control.clik import TargetError
from soft_arm_control.config import (FEEDBACKS, IDENTIFICATION, ControlConfig, TaskConfig,
                                     load_control_config, load_task_config)
from soft_arm_control.outer_loop import OuterLoop, outer_loop_for
from soft_arm_control.estimators import shape_estimator
from soft_arm_control.shape_estimation import (EstimatorConfig, fused_markers, fused_tip,
                                               load_estimator_config, prior_overrides)
from soft_arm_control.strike_planner import strike_move_for
from soft_arm_control.two_level import TwoLevelController
from soft_arm_control.target_margin import target_point
from soft_arm_drivers.mocap.bridge_config import calibration_overrides
from soft_arm_drivers.sim.plant_config import PlantConfig, load_plant_config, with_bridge_calibration
from soft_arm_drivers.sim.simulated_rig import SimulatedRig
from soft_arm_model import ArmConfig, build_model, load_arm_config
from soft_arm_model.parameters import default_config_dir, split_overrides

from .excitation import ExcitationConfig, load_excitation
from .metrics import summarise, tracking_metrics, transition_metrics
from .strike import measured_strike, plan_strike, rehearse, strike_metrics


@dataclass(frozen=True)
class Setup:
    """Everything a run needs: the controller's arm, controller, plant and task parameters (the
    identification experiment: no task, its ``excitation``), the shape estimator's parameters and
    what the online CLIK closes its loop on (``feedback``, one of
    :data:`~soft_arm_control.config.FEEDBACKS`)."""
    arm: ArmConfig
    control: ControlConfig
    plant: PlantConfig
    task: TaskConfig | None
    excitation: ExcitationConfig | None = None
    estimator: EstimatorConfig | None = None
    feedback: str = "mocap"


def load_setup(task: str, config_dir: str | None = None, overrides=None,
               arm_file: str | None = None, feedback: str = "mocap") -> Setup:
    """Load the parameter files from ``config_dir`` (default: the package's) with overrides
    (``namespace.key=value`` strings); ``arm_file``: the controller's arm description instead of
    ``arm.yaml`` (e.g. an identified one): the plant stays the arm of ``plant.yaml`` over
    ``arm.yaml`` (or ``plant.plant_file``), whatever the controller believes; the mocap
    calibration an arm file carries (``rig.mocap.calibration``, as soft-arm-identify writes it) is
    the one the markers come through, as the mocap bridge given that file would publish them, and
    the estimator priors it carries (``estimator.prior``) replace estimator.yaml's beneath
    ``overrides``. ``task`` "identification": the identification experiment of
    ``identification.yaml`` instead of a task. ``feedback``: what the online CLIK closes its loop
    on (mocap, fused or estimate)."""
    if feedback not in FEEDBACKS:
        raise ValueError(f"feedback must be one of {list(FEEDBACKS)}, got {feedback!r}")
    d = config_dir or default_config_dir()
    groups = split_overrides(overrides, ("arm", "control", "plant", "tasks", "identification", "estimator"))
    drawing = load_arm_config(os.path.join(d, "arm.yaml"), groups["arm"])
    arm = load_arm_config(arm_file, groups["arm"]) if arm_file else drawing
    plant = load_plant_config(arm, os.path.join(d, "plant.yaml"), groups["plant"])
    if arm_file:
        plant = with_bridge_calibration(replace(plant, drawing=drawing), os.path.join(d, "mocap.yaml"),
                                        calibration_overrides(arm_file))
    plant.plant_arm(arm)                  # a bad plant file is refused before anything runs
    control = load_control_config(arm, os.path.join(d, "control.yaml"),
                                  {**groups["control"], "clik.feedback": feedback})
    estimator = load_estimator_config(os.path.join(d, "estimator.yaml"), {
        **(prior_overrides(arm_file) if arm_file else {}), **groups["estimator"]})
    if task == IDENTIFICATION:
        return Setup(arm, control, plant, None, load_excitation(
            len(arm.tendons), control.tension_min, control.tension_max,
            os.path.join(d, "identification.yaml"), groups["identification"]), estimator, feedback)
    return Setup(arm, control, plant,
                 load_task_config(task, arm, os.path.join(d, "tasks.yaml"), groups["tasks"]),
                 estimator=estimator, feedback=feedback)


def add_setup_arguments(parser):
    """The options that say what a run simulates (soft-arm-harness, soft-arm-experiment): ``--config
    DIR``, repeated ``--set ns.key=value``, ``--plant-file FILE``, ``--arm-file FILE``,
    ``--feedback`` and ``--accept-closest``;
    :func:`setup_overrides` and :func:`check_targets` read them back."""
    parser.add_argument("--config", metavar="DIR", help="directory with the parameter files")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="NS.KEY=VALUE",
                        help="override one parameter (repeatable), e.g. plant.youngs_modulus_scale=1")
    parser.add_argument("--plant-file", metavar="FILE",
                        help="simulate the arm described by FILE (the schema of arm.yaml) as the plant, "
                             "whatever the controller believes")
    parser.add_argument("--arm-file", metavar="FILE",
                        help="the controller's arm description (the schema of arm.yaml, e.g. "
                             "identified) instead of the configuration's arm.yaml")
    parser.add_argument("--feedback", choices=FEEDBACKS, default="mocap",
                        help="what the online CLIK closes its loop on: the mocap's markers (default), "
                             "fused (the mocap's where seen, the shape estimate's elsewhere) or the "
                             "shape estimate (soft-arm-experiment: the shape_estimator node joins "
                             "the graph)")
    parser.add_argument("--accept-closest", action="store_true",
                        help="run a target the model cannot reach within the tension limits at the "
                             "closest point it can (printed), instead of refusing the task")


def setup_overrides(args) -> list:
    """The ``--set`` overrides of :func:`add_setup_arguments`, with ``--plant-file`` as a
    ``plant.plant_file`` override (absolute, so that every process of a run reads the same file)."""
    return args.sets + ([f"plant.plant_file={os.path.abspath(args.plant_file)}"] if args.plant_file else [])


@dataclass
class Record:
    """Time series of a run. Inner-loop rate: t_inner, tension, shortening (measured), shortening_ref,
    theta (the inner loop's coordinates of the measured shortenings), theta_ref. Mocap rate: t_mocap
    (exposure times), x (measured task coordinates, NaN where the markers were not seen), x_true, x_d,
    tip (the measured tip coordinates the task controls; all three if it controls none), tip_true, tip_speed
    (true),
    window (index of the transition); with a shape estimator, at the same exposures: markers_true
    (n_markers, 3), markers_estimated and marker_covariance (n_markers, 3, 3) [m^2] (the estimate's)
    and markers_seen (n_markers,) bool (in the frame exposed then). All SI."""
    t_inner: list = field(default_factory=list)
    tension: list = field(default_factory=list)
    shortening: list = field(default_factory=list)
    shortening_ref: list = field(default_factory=list)
    theta: list = field(default_factory=list)
    theta_ref: list = field(default_factory=list)
    t_mocap: list = field(default_factory=list)
    x: list = field(default_factory=list)
    x_true: list = field(default_factory=list)
    x_d: list = field(default_factory=list)
    tip: list = field(default_factory=list)
    tip_true: list = field(default_factory=list)
    tip_speed: list = field(default_factory=list)
    window: list = field(default_factory=list)
    markers_true: list = field(default_factory=list)
    markers_estimated: list = field(default_factory=list)
    marker_covariance: list = field(default_factory=list)
    markers_seen: list = field(default_factory=list)

    def arrays(self) -> dict:
        return {k: np.asarray(v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class Transition:
    """One window of the protocol: phase, mode, target index (0-based), x_d [m], start and end [s]."""
    phase: str
    mode: str
    target: int
    x_d: np.ndarray
    start: float
    end: float


@dataclass
class RunResult:
    """The outcome of :func:`run_experiment`: transitions, per-transition metrics, summary, record,
    the coordinates the inner loop regulated (``actuation_map``: the identity for the shortenings),
    the stored configurations per target, what the online CLIK did per goal
    (:meth:`~soft_arm_control.outer_loop.GoalReport.as_dict`, in transition order) and, with a
    pendulum, the strike: its ``plan``, what the ``simulated`` contact did
    (:func:`~.strike.strike_metrics`) and what the motion capture ``measured``
    (:func:`~.strike.measured_strike`); the track windows' figures
    (:class:`~.metrics.TrackingMetrics`), which the transitions and the summary leave out."""
    transitions: list
    metrics: list
    summary: object
    record: Record
    actuation_map: ActuationMap
    stored: dict
    goals: list
    strike: dict | None = None
    tracking: list = field(default_factory=list)


def window_metrics(task, transitions: list, rec: Record, truth: bool = False) -> tuple[list, list]:
    """The metrics of each of ``task``'s windows (``transitions``, :func:`run_experiment`'s) in the
    record ``rec``: the step windows' (:func:`~.metrics.transition_metrics`) and the track windows'
    (:func:`~.metrics.tracking_metrics`), of what the mocap measured or with ``truth`` of the
    plant's true markers. ValueError for a window no frame of the mocap saw."""
    phases = {ph.name: ph for ph in task.phases}
    arrays = rec.arrays()
    if truth:
        arrays["x"] = arrays["x_true"]
        arrays["tip"] = arrays["tip_true"]
    rows, tracking = [], []
    for w_index, tr in enumerate(transitions):
        sel = arrays["window"] == w_index
        if tr.mode == "track":
            tracking.append(tracking_metrics(tr.phase, tr.target + 1, phases[tr.phase].trajectory,
                                             arrays["t_mocap"][sel] - tr.start,
                                             arrays["x_d"][sel] - arrays["x"][sel],
                                             min(task.steady_time, 0.5 * (tr.end - tr.start))))
            continue
        rows.append(transition_metrics(tr.phase, tr.target + 1, arrays["t_mocap"][sel],
                                       arrays["x_d"][sel] - arrays["x"][sel], arrays["tip"][sel],
                                       arrays["tip_speed"][sel], task.steady_time,
                                       tr.end - tr.start))
    return rows, tracking


def goal_warning(goal: dict) -> str:
    """One line saying what went wrong with a goal of :attr:`RunResult.goals` (status not ok)."""
    head = f"target {goal['target']} ({goal['mode']})"
    closest = ("no online step was taken" if goal["closest_error"] is None
               else f"closest measured error {goal['closest_error'] * 1e3:.2f} mm")
    if goal["status"] == "unreached":
        return (f"{head} not reached: the last measured error was {goal['error'] * 1e3:.2f} mm when the "
                f"window ended; {closest}")
    if goal["status"] == "saturated":
        return (f"{head} is faster than the tendons can follow: on {goal['saturated_steps']} of "
                f"{goal['online_steps']} online steps the path's dynamic feedforward lay outside the "
                f"tension limits and was clipped; {closest}")
    if goal["status"] == "stalled":
        return (f"{head} stalled: the measured error stayed above the reach tolerance without falling "
                f"for the last {goal['stalled_steps']} of {goal['online_steps']} online steps, although "
                f"every step was feasible for the model (out of the arm's reach, or a load the model "
                f"lacks); {closest}")
    if goal["status"] == "untrusted":
        return (f"{head} held its precomputed reference: the trust region refused the estimate fed back "
                f"{goal['distrusts']} time(s), the last at {goal['distrust_time']:.2f} s "
                f"({goal['distrust']}); "
                f"{goal['untrusted_frames']} frames without an online step; {closest}")
    if goal["status"] == "uncertain":
        return (f"{head} held its reference: the estimated error, {goal['error'] * 1e3:.2f} mm at the "
                f"end, is within what the estimate's own uncertainty explains (clik.trust.confidence "
                f"standard deviations); on {goal['uncertain_frames']} frames the step took less than all "
                f"of it or none, {goal['online_steps']} online steps")
    return (f"{head} is infeasible for the model from where the online CLIK got: "
            f"{goal['infeasible_steps']} of {goal['online_steps']} steps projected onto the tension "
            f"limits, {goal['held_steps']} held; {closest}")


def schedule(task: TaskConfig) -> list:
    """The protocol as (phase, mode, target, window) tuples in order."""
    return [(ph.name, ph.mode, k, ph.window) for ph in task.phases for k in ph.sequence]


def _clik_targets(task: TaskConfig) -> list:
    """The targets (0-based) a clik or precomputed phase visits, in order."""
    return sorted({k for _, mode, k, _ in schedule(task) if mode in ("clik", "precomputed")})


def precompute_targets(outer: OuterLoop, control: ControlConfig, task: TaskConfig) -> dict:
    """Precomputed references of every target a clik phase visits, each solved from the start-up
    pose (or the nearest seed equilibrium), so that a reference does not depend on the visiting
    order. Raises TargetError, before anything moves, for an unreachable, infeasible or fragile
    target (:func:`target_point`); its message names the point --accept-closest would run."""
    points = {}
    for k in _clik_targets(task):
        x_d = np.array(task.targets[k])
        try:
            points[k] = target_point(outer, control, task, x_d)
        except TargetError as exc:
            if exc.closest is None:
                raise TargetError(f"target {k + 1} of {task.name}: {exc}; no equilibrium within the "
                                  "limits that can be held was found near it") from exc
            closest = exc.closest.x
            raise TargetError(
                f"target {k + 1} of {task.name}: {exc}. The closest point the model holds within "
                f"the limits is {closest.round(4).tolist()} m "
                f"({np.linalg.norm(closest - x_d) * 1e3:.1f} mm away): --accept-closest runs the "
                "task with it", exc.closest) from exc
    return points


def check_targets(setup: Setup, accept_closest: bool = False) -> tuple[list, list]:
    """Every target a clik phase visits, solved on the controller's model before anything moves:
    (overrides, notes). Without ``accept_closest`` a target the model cannot hold (unreachable,
    infeasible or fragile) raises TargetError (:func:`precompute_targets`). With it, such a target
    is replaced by the point :func:`target_point` offers, given back as a ``tasks.<task>.targets``
    override (none when every target can be held), with a note per replaced target."""
    task = setup.task
    if task is None:                          # the identification experiment: tensions, no targets
        return [], []
    outer = outer_loop_for(build_model(setup.arm), setup.control, task)
    if not accept_closest:
        precompute_targets(outer, setup.control, task)
        return [], []
    targets, notes = [list(x) for x in task.targets], []
    for k in _clik_targets(task):
        x_d = np.array(task.targets[k])
        try:
            target_point(outer, setup.control, task, x_d)
        except TargetError as exc:
            if exc.closest is None:
                raise
            targets[k] = [round(float(v), 7) for v in exc.closest.x]
            notes.append(f"target {k + 1} of {task.name} {x_d.round(4).tolist()} m replaced by the closest "
                         f"point the model holds {targets[k]} m "
                         f"({np.linalg.norm(np.array(targets[k]) - x_d) * 1e3:.1f} mm away; "
                         f"{_reason(exc)})")
    if not notes:
        return [], []
    flat = ", ".join(str(v) for x in targets for v in x)
    return [f"tasks.{task.name}.targets=[{flat}]"], notes


def load_setup_at_closest(task: str, config_dir: str | None = None, overrides=(), arm_file: str | None = None,
                          feedback: str = "mocap") -> tuple[Setup, list]:
    """:func:`load_setup` with every target the controller's model cannot hold replaced by the
    closest point it holds (``--accept-closest``): the setup and :func:`check_targets`' notes, one
    per replaced target."""
    setup = load_setup(task, config_dir, list(overrides), arm_file, feedback)
    closest, notes = check_targets(setup, accept_closest=True)
    if closest:
        setup = load_setup(task, config_dir, list(overrides) + closest, arm_file, feedback)
    return setup, notes


def _reason(exc: TargetError) -> str:
    """The first reason of a refusal, for a one-line note."""
    text = str(exc)
    if " is fragile: " in text:
        return "fragile: " + text.partition(" is fragile: ")[2].partition(":")[0]
    return text.partition(": ")[2].partition(";")[0]


def run_experiment(setup: Setup, progress=None, actuation_map: ActuationMap | None = None,
                   estimate: bool = False, truth: bool = False, observer=None) -> RunResult:
    """Run the task's protocol on the simulated rig and compute the paper's metrics.

    ``progress(t, t_end)`` is called about once per simulated second. The shape estimator runs at
    every mocap exposure (the encoders and tensions of that instant, the markers of the latest
    frame delivered since the last update) when the CLIK's ``setup.feedback`` needs it or
    ``estimate`` asks for it (its estimate is then in the record); with fused or estimate
    feedback the online CLIK takes its task coordinates from it at each update instead of from
    the delivered frames. The metrics are of what the mocap measured, or with ``truth`` of the
    plant's true markers (a run whose mocap is lost has no measured figures). ``observer(t, rig,
    frame, estimate, x_d, reference)`` is called at every mocap exposure (``estimate`` None without
    the estimator; ``x_d`` the target now [m], ``reference`` the inner loop's): the live view's.
    """
    ctl, task, pc = setup.control, setup.task, setup.plant
    model = build_model(setup.arm)
    ctrl = TwoLevelController(model, ctl, task, actuation_map)
    pretension = np.full(model.n_tendons, ctl.tension_min)
    outer = ctrl.outer
    start = ctrl.reference = outer.start           # the controller's view of start-up
    points = precompute_targets(outer, ctl, task)
    rig = SimulatedRig(build_model(pc.plant_arm(setup.arm)), pc, start.shortening, pretension,
                       task.payload, task.pendulum)
    plan = None
    if task.pendulum is not None:            # the strike is the first window (precomputed)
        first = schedule(task)[0]
        move = strike_move_for(model, ctl, task, points[first[2]])
        arm_time, gap = rehearse(model, ctl, task, ctrl.actuation_map, points[first[2]], first[3], move)
        plan = plan_strike(task, arm_time, gap, 1.0 / ctl.inner_rate, move)

    dt = pc.timestep
    inner_every = max(1, int(round(1.0 / (ctl.inner_rate * dt))))
    rec = Record()
    transitions = []
    tip_index = model.marker_X.size - 1
    tip_axes = [a for k, a in zip(task.space.markers, task.space.axes) if k == tip_index] or [0, 1, 2]
    space = task.space
    estimator = None
    if estimate or setup.feedback != "mocap":
        estimator = shape_estimator(model, setup.estimator or load_estimator_config(), ctl.rotor_mass)
    latest = None                # markers of the latest frame delivered since the last estimate
    u = pretension.copy()
    balls = []                   # (exposure time, ball marker, tip marker) of the strike's frames
    total = sum(w for *_, w in schedule(task))
    second = int(round(1.0 / dt))
    t_start = 0.0
    phases = {ph.name: ph for ph in task.phases}
    for w_index, (phase, mode, k, window) in enumerate(schedule(task)):
        x_d = np.array(task.targets[k])
        send_at = t_start + (plan.send_delay if plan is not None and w_index == 0 else 0.0)
        release_at = t_start + plan.release_delay if plan is not None and w_index == 0 else np.inf
        sent = False
        t_end = t_start + window
        while rig.t < t_end - 1e-9:
            t = rig.t
            if not sent and t >= send_at - 1e-9:
                ctrl.reference = outer.goal(t, x_d, mode, points.get(k), phases[phase].trajectory,
                                            plan.move if plan is not None and w_index == 0 else None)
                sent = True
            if t >= release_at - 1e-9:
                rig.release_pendulum()
            frame, delivered = rig.begin_step()
            if frame is not None:
                rec.t_mocap.append(frame.stamp)
                rec.x.append(space.from_markers(frame.markers))
                rec.x_true.append(space.from_markers(frame.true_markers))
                rec.x_d.append(phases[phase].target_at(x_d, frame.stamp - t_start))
                rec.tip.append(frame.markers[tip_index, tip_axes])
                rec.tip_true.append(frame.true_markers[tip_index, tip_axes])
                rec.tip_speed.append(frame.tip_speed)
                rec.window.append(w_index)
                if frame.ball is not None:
                    balls.append((frame.stamp, frame.ball, frame.markers))
            if delivered:
                latest = delivered[-1].markers
            x_feedback = sigma = estimated = None
            if estimator is not None and frame is not None:
                s, sd = rig.tendons()
                estimator.update(t, s, sd, rig.tension, latest)
                estimated = estimator.estimate()
                rec.markers_true.append(frame.true_markers)
                rec.markers_estimated.append(estimated.markers)
                rec.marker_covariance.append(estimated.marker_covariance)
                rec.markers_seen.append(frame.visible)
                defended = estimated.defended(estimator.config.max_sigma)
                # the fused tip's uncertainty for either: none where the mocap saw the tip (the
                # estimate is then held to a measurement), the estimate's elsewhere
                sigma = space.tip_sigma(fused_tip(latest, estimated)[1])
                if setup.feedback == "fused":
                    x_feedback = space.from_markers(fused_markers(latest, defended))
                elif setup.feedback == "estimate":
                    x_feedback = space.from_markers(defended)
                latest = None
            if observer is not None and frame is not None:
                observer(t, rig, frame, estimated, rec.x_d[-1], ctrl.reference)
            if setup.feedback == "mocap" and delivered:
                x_feedback = space.from_markers(delivered[-1].markers)
            if x_feedback is not None:
                ref = outer.frame(t, x_feedback, sigma)
                if ref is not None:
                    ctrl.reference = ref
            if rig.step_index % inner_every == 0:
                s, sd = rig.tendons()
                u = ctrl.inner(t, s, sd)
                rec.t_inner.append(t)
                rec.tension.append(u)
                rec.shortening.append(s)
                rec.shortening_ref.append(ctrl.reference.shortening)
            rig.end_step(u)
            if progress is not None and rig.step_index % second == 0:
                progress(rig.t, total)
        transitions.append(Transition(phase, mode, k, x_d, t_start, t_end))
        t_start = t_end
    outer.finish()
    rec.theta = list(ctrl.actuation_map.batch(rec.shortening))
    rec.theta_ref = list(ctrl.actuation_map.batch(rec.shortening_ref))
    rows, tracking = window_metrics(task, transitions, rec, truth)
    stored = {k: outer.stored[outer.key(x)] for k, x in enumerate(task.targets)
              if outer.key(x) in outer.stored}
    strike = None
    if plan is not None:
        strike = {"plan": plan.as_dict(), "simulated": strike_metrics(rig.strike, pc.timestep),
                  "measured": {"struck": False}}
        if rig.strike.release_time is not None and balls:
            t_b, ball, markers = (np.array(v) for v in zip(*balls))
            strike["measured"] = measured_strike(task.pendulum, rig.strike.release_time, t_b, ball, markers,
                                                 setup.arm)
    return RunResult(transitions, rows, summarise(rows), rec, ctrl.actuation_map, stored,
                     [g.as_dict() for g in outer.reports], strike, tracking)
