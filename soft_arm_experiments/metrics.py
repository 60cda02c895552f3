"""The paper's task-space metrics (Results; Table 1) from sampled task errors.

For each transition (one target held for one time window):

- the time to reach and remain within a band: every controlled coordinate's error below the band
  from that sample to the end of the window (cm band: 3 cm, mm band: 1 cm);
- the equivalent task velocity: tip displacement over the window [m] / that time [s], the
  displacement measured along the tip coordinates the task controls (a 2D task on the tip's x and z
  does not count its uncontrolled y); none when every coordinate is within the band already;
- the RMS of the task error norm over the steady-state part (the last ``steady_time`` seconds);
- the peak tip speed [m/s] (true, or from measured positions: :func:`measured_speed`).

The metrics are of what the mocap saw: a sample whose task or tip markers were occluded (NaN) is
left out, and a window in which no frame saw them is an error (ValueError), never a figure.

The summary row reports, like Table 1, the best (largest) task velocities over all transitions that
reached the band, the peak tip speed, and the steady-state RMS error of the transitions with the
longest window.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

CM_BAND = 0.03  # m
MM_BAND = 0.01  # m


def settling_time(t, error, band: float) -> float | None:
    """Time [s] from t[0] until ``|error|`` stays below ``band`` on every coordinate to the end; None if
    the last sample is outside the band. ``error``: (N, m) [m]; t: (N,) [s], increasing."""
    t = np.asarray(t, dtype=float)
    inside = np.all(np.abs(np.asarray(error, dtype=float)) < band, axis=1)
    if inside.size == 0 or not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    first = 0 if outside.size == 0 else outside[-1] + 1
    return float(t[first] - t[0])


SPEED_BASELINE = 0.01  # s: measured tip speeds are differences over at least this long


def measured_speed(t, positions, baseline: float = SPEED_BASELINE) -> np.ndarray:
    """Speed [m/s] at each sample of measured positions (N, 3) [m] at ascending times t (N,) [s]:
    the displacement from the latest sample at least ``baseline`` > 0 [s] earlier over the time
    between them (0 before the first such sample). Mocap frames of a rig are not evenly spaced: two
    frames 0.1 ms apart would turn 0.2 mm of marker noise into 2 m/s. Samples with occluded (NaN)
    positions are skipped, and their speed is NaN."""
    if not baseline > 0:
        raise ValueError(f"baseline must be > 0 s, got {baseline}")
    t_all = np.asarray(t, dtype=float)
    p_all = np.asarray(positions, dtype=float)
    seen = np.all(np.isfinite(p_all), axis=1)
    t, p = t_all[seen], p_all[seen]
    j = np.searchsorted(t, t - baseline, side="right") - 1
    speed = np.zeros(t.size)
    ok = j >= 0
    speed[ok] = np.linalg.norm(p[ok] - p[j[ok]], axis=1) / (t[ok] - t[j[ok]])
    out = np.full(t_all.size, np.nan)
    out[seen] = speed
    return out


@dataclass(frozen=True)
class TransitionMetrics:
    """Metrics of one transition: phase name, target index (1-based), window [s], tip displacement
    [m], band times [s] and task velocities [m/s] (None: band not reached and kept), steady-state RMS
    error norm [m], final error norm [m], peak tip speed [m/s]."""
    phase: str
    target: int
    window: float
    displacement: float
    time_cm: float | None
    time_mm: float | None
    velocity_cm: float | None
    velocity_mm: float | None
    rms_steady: float
    final_error: float
    peak_speed: float


def transition_metrics(phase: str, target: int, t, error, tip, tip_speed, steady_time: float = 2.0,
                       window: float | None = None) -> TransitionMetrics:
    """Metrics of one window: samples t [s] (N,), task errors (N, m) [m], measured tip coordinates
    (N, k) [m] (those the task controls) and true tip speeds (N,) [m/s]. The steady part is the last
    ``steady_time`` seconds, at most half the window; ``window`` [s] defaults to the span of the samples."""
    t, error, tip = (np.asarray(v, dtype=float) for v in (t, error, tip))
    seen = np.all(np.isfinite(error), axis=1) & np.all(np.isfinite(tip), axis=1)
    if np.count_nonzero(seen) < 2:
        raise ValueError(f"the {phase} window of target {target}: {np.count_nonzero(seen)} of {t.size} "
                         "frames saw the task's markers, no metrics")
    window = float(t[-1] - t[0]) if window is None else float(window)
    t, error, tip = t[seen], error[seen], tip[seen]
    displacement = float(np.linalg.norm(tip[-1] - tip[0]))
    times = {band: settling_time(t, error, band) for band in (CM_BAND, MM_BAND)}

    def velocity(tb, band):
        # none when the band holds from the first sample: a diagonal move can be longer than the
        # band while every coordinate starts inside it (the band is per coordinate)
        if tb is None or tb == 0.0 or displacement <= band:
            return None
        return displacement / tb

    steady = t >= t[-1] - min(steady_time, 0.5 * window)
    norms = np.linalg.norm(error, axis=1)
    return TransitionMetrics(
        phase=phase, target=int(target), window=round(window, 6), displacement=displacement,
        time_cm=times[CM_BAND], time_mm=times[MM_BAND],
        velocity_cm=velocity(times[CM_BAND], CM_BAND), velocity_mm=velocity(times[MM_BAND], MM_BAND),
        rms_steady=float(np.sqrt(np.mean(norms[steady] ** 2))), final_error=float(norms[-1]),
        peak_speed=float(np.max(np.asarray(tip_speed, dtype=float)[seen])))


@dataclass(frozen=True)
class Summary:
    """A Table 1 row: steady-state RMS task error [m] (longest-window transitions), the best cm- and
    mm-band task velocities [m/s] (None if no transition reached the band), peak tip speed [m/s],
    and how many transitions reached each band out of ``transitions``."""
    rms_error: float
    velocity_cm: float | None
    velocity_mm: float | None
    peak_speed: float
    reached_cm: int
    reached_mm: int
    transitions: int


def summarise(rows: list[TransitionMetrics]) -> Summary:
    """The Table 1 row of a list of transitions."""
    if not rows:
        raise ValueError("no transitions to summarise")
    longest = max(r.window for r in rows)
    steady = [r.rms_steady for r in rows if r.window >= longest - 1e-9]

    def best(values):
        values = [v for v in values if v is not None]
        return max(values) if values else None

    return Summary(
        rms_error=float(np.sqrt(np.mean(np.square(steady)))),
        velocity_cm=best(r.velocity_cm for r in rows), velocity_mm=best(r.velocity_mm for r in rows),
        peak_speed=max(r.peak_speed for r in rows),
        reached_cm=sum(r.time_cm is not None for r in rows),
        reached_mm=sum(r.time_mm is not None for r in rows), transitions=len(rows))


def _fmt(v, scale=1.0, digits=3):
    return "-" if v is None else f"{v * scale:.{digits}f}"


def format_table(rows: list[TransitionMetrics], summary: Summary,
                 paper_peak_speed: float | None = None) -> str:
    """Per-transition table and the paper-style summary row, as plain text (with the peak tip
    speed the paper reports for the task [m/s], if given)."""
    lines = [f"{'phase':<10} {'tgt':>3} {'win[s]':>6} {'disp[m]':>7} {'t_cm[s]':>7} {'t_mm[s]':>7} "
             f"{'v_cm':>6} {'v_mm':>6} {'rms[mm]':>7} {'final[mm]':>9} {'peak[m/s]':>9}"]
    for r in rows:
        lines.append(f"{r.phase:<10} {r.target:>3} {r.window:>6.1f} {r.displacement:>7.3f} "
                     f"{_fmt(r.time_cm, 1, 2):>7} {_fmt(r.time_mm, 1, 2):>7} {_fmt(r.velocity_cm):>6} "
                     f"{_fmt(r.velocity_mm):>6} {r.rms_steady * 1e3:>7.2f} {r.final_error * 1e3:>9.2f} "
                     f"{r.peak_speed:>9.2f}")
    lines += ["",
              "Table 1 row (paper, CLIK + PID+ on hardware: RMS 0.67 mm, 0.063 m/s mm band, "
              "0.384 m/s cm band)",
              f"  task-space RMS error [mm]      {summary.rms_error * 1e3:.2f}",
              f"  task velocity, mm band [m/s]   {_fmt(summary.velocity_mm)} "
              f"({summary.reached_mm}/{summary.transitions} transitions reached)",
              f"  task velocity, cm band [m/s]   {_fmt(summary.velocity_cm)} "
              f"({summary.reached_cm}/{summary.transitions} transitions reached)",
              f"  peak tip speed [m/s]           {summary.peak_speed:.2f}"
              + ("" if paper_peak_speed is None else f" (the paper's arm: {paper_peak_speed:.2f})")]
    return "\n".join(lines)


@dataclass(frozen=True)
class TrackingMetrics:
    """One track window: phase, target (1-based, the path's start), the trajectory's shape, size
    [m] and period [s], its mean path speed [m/s], and the RMS and maximum of the task error norm
    [m] from ``settle`` [s] after the window's start to its end; ``last_period_rms_error`` [m]: the
    RMS over the window's last period (what a learned path has come to; None when the window is
    not a period longer than ``settle``)."""
    phase: str
    target: int
    shape: str
    size: float
    period: float
    path_speed: float
    settle: float
    rms_error: float
    max_error: float
    last_period_rms_error: float | None = None


def tracking_metrics(phase: str, target: int, trajectory, t, errors, settle: float) -> TrackingMetrics:
    """Tracking figures of one window: mocap times t [s] from the window's start and the task
    errors (N, m) [m] against the moving target."""
    t = np.asarray(t, dtype=float)
    norm = np.linalg.norm(np.asarray(errors, dtype=float), axis=1)
    t, norm = t[np.isfinite(norm)], norm[np.isfinite(norm)]          # frames that saw the markers
    counted = t >= settle
    if not np.any(counted):
        raise ValueError(f"no frame after the settling time ({settle} s) of the {phase} window")
    last = None
    if t[-1] - trajectory.period >= settle:
        last = float(np.sqrt(np.mean(norm[t > t[-1] - trajectory.period] ** 2)))
    return TrackingMetrics(phase, target, trajectory.shape, trajectory.size, trajectory.period,
                           trajectory.path_speed(), settle, float(np.sqrt(np.mean(norm[counted] ** 2))),
                           float(norm[counted].max()), last)


def format_tracking(rows: list[TrackingMetrics]) -> str:
    """The track windows as a table: error against path speed."""
    lines = ["Tracking (online CLIK with the trajectory's velocity as feedforward)",
             f"{'phase':<12} {'shape':<8} {'size[mm]':>8} {'period[s]':>9} {'speed[m/s]':>10} "
             f"{'rms[mm]':>7} {'max[mm]':>7} {'last period rms[mm]':>19}"]
    for r in rows:
        last = "-" if r.last_period_rms_error is None else f"{r.last_period_rms_error * 1e3:.2f}"
        lines.append(f"{r.phase:<12} {r.shape:<8} {r.size * 1e3:>8.1f} {r.period:>9.1f} "
                     f"{r.path_speed:>10.4f} {r.rms_error * 1e3:>7.2f} {r.max_error * 1e3:>7.2f} {last:>19}")
    return "\n".join(lines)


def to_json(rows: list[TransitionMetrics], summary: Summary) -> dict:
    """A JSON-ready dict of the transitions and the summary (SI units)."""
    return {"summary": asdict(summary), "transitions": [asdict(r) for r in rows]}
