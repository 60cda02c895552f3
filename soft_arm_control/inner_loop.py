"""The inner loop: the paper's collocated P-satI-D+ law on tendon-length-based actuation coordinates.

    u = G_P (theta_d - theta) + G_D (thetadot_d - thetadot) + G_I xi + u_ff,
    xi' = e_sat tanh((theta_d - theta) / e_sat)

(paper eq. PID+; e_sat = 1 m is the paper's literal tanh of the error in metres, a smaller e_sat
bounds the integrator rate to e_sat per second per tendon while keeping the small-error slope 1).
theta is what ``control.inner_loop.coordinates`` names: the measured shortenings s [m] themselves
(the default: the motors' coordinates, in which the tensions' work u . sdot is exact, so that the
proportional term is the gradient of a potential and the loop passive whatever the friction), or the
paper's thetabar_a(s) (:mod:`.actuation_map`), which is not monotone in s (docs/decisions/0021).
thetadot by the chain rule from the measured shortening rates, theta_d = theta(s_d) from the
reference shortenings, u_ff = K_theta_a(q_d) + F_theta_a(q_d) [N] from the outer loop. thetadot_d is the
reference's own rate, by the chain rule from the reference's shortening rates: zero for a fixed
reference (the paper's law, -G_D thetadot), the online CLIK's rate while it moves the reference
(a tracked trajectory), so that the derivative term damps the arm's motion about the moving
reference instead of dragging against the motion asked for.

Tensions are clipped to [u_min, u_max] (pull only, u_min a small pretension) after an optional rate
limit (from the last output, u_min at the start: the first update, which has no interval, keeps
it); the integral is frozen while the clipped output saturates in the direction it would push it
(conditional integration, anti-windup). The core takes explicit time stamps [s] and never reads a
clock; its time is a :class:`~.loop_clock.LoopClock` of those stamps, so that a stamp that is no
number is refused before anything changes and a clock step (a stamp far ahead, or one that goes
back) is counted and integrated over as one period: the loop goes on. Tendons that the task does
not use hold u_min.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numba import njit

from .actuation_map import SCALE, ActuationMap, _feature_jacobian, _features
from .loop_clock import LoopClock

MAX_TIME_STEP = 0.1     # s: the longest gap between two states integrated over (50 periods at 500 Hz)


@dataclass(frozen=True)
class InnerLoopGains:
    """Diagonal gains per actuated tendon: proportional [N/m], derivative [N s/m], integral
    [N/(m s)]; integral saturation e_sat [m]; tension limits [N]; rate limit [N/s] (0: none)."""
    proportional: np.ndarray
    derivative: np.ndarray
    integral: np.ndarray
    integral_saturation: float
    tension_min: float
    tension_max: float
    tension_rate_limit: float = 0.0

    def __post_init__(self):
        for name in ("proportional", "derivative", "integral"):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.ndim != 1 or not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"{name} gains must be finite and >= 0, got {v}")
            object.__setattr__(self, name, v)
        if not (self.proportional.size == self.derivative.size == self.integral.size):
            raise ValueError("proportional, derivative and integral need one gain per tendon each")
        if not self.integral_saturation > 0:
            raise ValueError(f"integral_saturation must be > 0 m, got {self.integral_saturation}")
        if not 0 <= self.tension_min < self.tension_max:
            raise ValueError(f"need 0 <= tension_min < tension_max, got {self.tension_min}, "
                             f"{self.tension_max}")
        if not self.tension_rate_limit >= 0:
            raise ValueError(f"tension_rate_limit must be >= 0 N/s, got {self.tension_rate_limit}")


class PSatID:
    """P-satI-D+ regulator for the tendons ``active`` (0-based) of an arm with ``n_tendons`` tendons.

    ``update`` takes and returns arrays over all tendons; the inactive ones get u_min. The integral
    state ``xi`` [m s] is public for inspection and is kept across reference changes. ``clock``: the
    loop's time from the update stamps, ``max_time_step`` [s] the longest gap integrated over.
    """

    def __init__(self, gains: InnerLoopGains, actuation_map: ActuationMap, active, n_tendons: int,
                 max_time_step: float = MAX_TIME_STEP):
        self.gains = gains
        self.max_time_step = float(max_time_step)
        self.clock = LoopClock(self.max_time_step)
        self.active = np.array(active, dtype=int)
        if self.active.size != gains.proportional.size:
            raise ValueError(f"{self.active.size} active tendons but {gains.proportional.size} gains")
        self.n_tendons = n_tendons
        self.xi = np.zeros(self.active.size)
        self.u = np.full(n_tendons, gains.tension_min)
        identity = actuation_map.coef is None
        self._exponents = np.zeros((0, n_tendons), dtype=np.int64) if identity else actuation_map.exponents
        self._coef = np.zeros((0, 0)) if identity else np.ascontiguousarray(actuation_map.coef)
        # compile the kernel here (a cold numba cache: a fresh install), not in the first control
        # period that meets a reference
        zeros = np.zeros(n_tendons)
        self._fixed = zeros                  # the rate of a fixed reference (no allocation per update)
        _p_sat_i_d(zeros, zeros, zeros, zeros, np.zeros(self.active.size), self.active,
                   self._exponents, self._coef, gains.proportional, gains.derivative, gains.integral,
                   gains.integral_saturation, gains.tension_min, gains.tension_max, 0.0, -1.0,
                   np.zeros(self.active.size), self.u, np.empty(n_tendons))

    @property
    def t(self):
        """The last time stamp taken [s] (None before the first)."""
        return self.clock.stamp

    def reset(self):
        """Forget the integral, the last output and the time stamps."""
        self.xi[:] = 0.0
        self.u[:] = self.gains.tension_min
        self.clock = LoopClock(self.max_time_step)

    def update(self, t: float, s, s_dot, s_ref, u_ff, s_ref_dot=None) -> np.ndarray:
        """Tensions [N] of all tendons at time t [s].

        s, s_dot: measured shortenings [m] and rates [m/s] of all tendons; s_ref: reference
        shortenings [m] of all tendons (from q_d); u_ff: feedforward tensions [N] of the active
        tendons; s_ref_dot: the reference's shortening rates [m/s] of all tendons (None: a fixed
        reference). A non-finite input or time stamp raises ValueError and leaves the state
        unchanged; a clock step is integrated over as one period (module docstring). One compiled
        kernel (:func:`_p_sat_i_d`), some 10 us.
        """
        advance = self.clock.check(t)
        s_ref_dot = self._fixed if s_ref_dot is None else s_ref_dot
        s, s_dot, s_ref, u_ff, s_ref_dot = (np.ascontiguousarray(v, dtype=float)
                                            for v in (s, s_dot, s_ref, u_ff, s_ref_dot))
        dt = advance.dt
        g = self.gains
        # the first update after the start or a reset has no interval (dt 0): with a limit on, its
        # output stays at the last one (u_prev, tension_min), as the limit allows no step in no time
        rate_step = g.tension_rate_limit * dt if g.tension_rate_limit > 0 else -1.0
        xi, u = self.xi.copy(), np.empty(self.n_tendons)
        if not _p_sat_i_d(s, s_dot, s_ref, s_ref_dot, u_ff, self.active, self._exponents, self._coef,
                          g.proportional, g.derivative, g.integral, g.integral_saturation,
                          g.tension_min, g.tension_max, dt, rate_step, xi, self.u, u):
            raise ValueError("non-finite measurement, reference or feedforward")
        self.xi, self.u = xi, u
        self.clock.commit(t, advance)
        return u.copy()


@njit(cache=True, nogil=True)
def _p_sat_i_d(s, s_dot, s_ref, s_ref_dot, u_ff, active, exponents, coef, kp, kd, ki, e_sat, u_min,
               u_max, dt, rate_step, xi, u_prev, u_out) -> bool:
    """One P-satI-D+ update (the module docstring's law) into ``u_out`` [N] (all tendons) and ``xi``
    [m s] (active tendons), from the previous output ``u_prev`` [N]. The actuation map is the
    polynomial ``coef`` (n_t, F) in the monomials ``exponents`` (F, n_t) of s / SCALE, or the
    identity when ``coef`` has no rows; ``rate_step`` [N]: the rate limit's step this update (< 0:
    none; 0, a repeated stamp: the output holds). False, and nothing written, when an input is not
    finite."""
    n = s.shape[0]
    for k in range(n):
        if not (np.isfinite(s[k]) and np.isfinite(s_dot[k]) and np.isfinite(s_ref[k])
                and np.isfinite(s_ref_dot[k])):
            return False
    for i in range(u_ff.shape[0]):
        if not np.isfinite(u_ff[i]):
            return False
    identity = coef.shape[0] == 0
    n_f = exponents.shape[0]
    f, f_ref, f_jac = np.empty(n_f), np.empty(n_f), np.empty((n_f, n))
    f_rate = np.zeros(n_f)                    # d monomial / dt [1/s] from the shortening rates
    f_ref_rate = np.zeros(n_f)                # the same from the reference's rates
    moving = False
    for k in range(n):
        moving = moving or s_ref_dot[k] != 0.0
    if not identity:
        _features(s / SCALE, exponents, f)
        _features(s_ref / SCALE, exponents, f_ref)
        _feature_jacobian(s / SCALE, exponents, f_jac)
        for j in range(n_f):
            for m in range(n):
                f_rate[j] += f_jac[j, m] * s_dot[m] / SCALE
        if moving:
            _feature_jacobian(s_ref / SCALE, exponents, f_jac)
            for j in range(n_f):
                for m in range(n):
                    f_ref_rate[j] += f_jac[j, m] * s_ref_dot[m] / SCALE
    for k in range(n):
        u_out[k] = u_min
    for i in range(active.shape[0]):
        k = active[i]
        if identity:
            theta, theta_ref, theta_dot, theta_ref_dot = s[k], s_ref[k], s_dot[k], s_ref_dot[k]
        else:
            theta, theta_ref, theta_dot, theta_ref_dot = 0.0, 0.0, 0.0, 0.0
            for j in range(n_f):
                theta += coef[k, j] * f[j]
                theta_ref += coef[k, j] * f_ref[j]
                theta_dot += coef[k, j] * f_rate[j]
                theta_ref_dot += coef[k, j] * f_ref_rate[j]
        e = theta_ref - theta
        x = xi[i] + dt * e_sat * np.tanh(e / e_sat)
        u_pd = kp[i] * e + kd[i] * (theta_ref_dot - theta_dot) + u_ff[i]
        u_raw = u_pd + ki[i] * x
        # conditional integration: keep the old integral where the output saturates and the
        # integral would push it further out
        if (u_raw > u_max and x > xi[i]) or (u_raw < u_min and x < xi[i]):
            x = xi[i]
        u_a = u_pd + ki[i] * x
        if rate_step >= 0:
            u_a = min(max(u_a, u_prev[k] - rate_step), u_prev[k] + rate_step)
        xi[i] = x
        u_out[k] = min(max(u_a, u_min), u_max)
    return True


class TendonController:
    """The inner loop as a node runs it: P-satI-D+ on the ``active`` tendons (the task's), the
    others held at their feedforward tension.

    ``set_reference(s_ref, u_ff, s_ref_dot)``: reference shortenings [m], feedforward tensions [N]
    and the reference's shortening rates [m/s] of all tendons (the shortenings of the tendons that
    are not actuated matter too: thetabar_a is a function of all of them). Before any reference
    every tendon holds ``tension_min``. Without ``feedforward`` the regulated tendons get no
    feedforward tension (the integral has to find it). The reference's rate counts for
    ``rate_hold`` seconds of the inner loop's own time (:attr:`clock`) from the first update after it
    arrived, then as zero: a reference that stops coming (the outer loop stalled, its frames lost) is
    a fixed one, not one that keeps moving.
    """

    def __init__(self, n_tendons: int, gains: InnerLoopGains, actuation_map: ActuationMap, active,
                 feedforward: bool = True, rate_hold: float = 0.0, max_time_step: float = MAX_TIME_STEP):
        self.n, self.gains, self.feedforward = n_tendons, gains, feedforward
        self.rate_hold = float(rate_hold)
        self.active = [int(k) for k in active]
        self.pid = PSatID(self._active_gains(gains), actuation_map, self.active, n_tendons, max_time_step)
        self.s_ref = None
        self.s_ref_dot = np.zeros(n_tendons)
        self._rate_since = None              # inner-loop time the current rate was first used [s]
        self.u_ff = np.full(n_tendons, gains.tension_min)

    def _active_gains(self, gains: InnerLoopGains) -> InnerLoopGains:
        if gains.proportional.size != self.n:
            raise ValueError(f"the gains need one value per tendon ({self.n}), got {gains.proportional.size}")
        a = self.active
        return replace(gains, proportional=gains.proportional[a], derivative=gains.derivative[a],
                       integral=gains.integral[a])

    def set_gains(self, gains: InnerLoopGains):
        """New gains and limits (over all tendons) from the next update on. The integral's tension
        G_I xi is kept where the old and new integral gains are both above zero (xi rescaled: a
        gain changed while the arm holds a load steps no tension); where either is zero the state
        is kept as it is. ValueError, with the old gains in place, when they do not fit the arm."""
        active = self._active_gains(gains)
        old, new = self.pid.gains.integral, active.integral
        both = (old > 0) & (new > 0)
        scale = np.ones_like(old)
        scale[both] = old[both] / new[both]
        self.pid.xi = self.pid.xi * scale
        self.pid.gains, self.gains = active, gains

    def set_reference(self, s_ref, u_ff, s_ref_dot=None):
        """A new reference (see the class); ``s_ref_dot`` None: a fixed reference."""
        s_ref, u_ff = np.asarray(s_ref, dtype=float), np.asarray(u_ff, dtype=float)
        rate = np.zeros(self.n) if s_ref_dot is None else np.asarray(s_ref_dot, dtype=float)
        if s_ref.shape != (self.n,) or u_ff.shape != (self.n,) or rate.shape != (self.n,) or not (
                np.all(np.isfinite(s_ref)) and np.all(np.isfinite(u_ff)) and np.all(np.isfinite(rate))):
            raise ValueError(f"a reference needs {self.n} finite shortenings and tensions (and "
                             f"{self.n} finite shortening rates, or none)")
        self.s_ref, self.u_ff = s_ref, u_ff
        self.s_ref_dot, self._rate_since = rate, None

    @property
    def clock(self) -> LoopClock:
        """The loop's time and its clock steps (the regulator's)."""
        return self.pid.clock

    def update(self, t: float, s, s_dot) -> np.ndarray:
        """Tensions [N] of all tendons at time t [s] from measured shortenings [m] and rates [m/s].
        A stamp that is no number raises ValueError and changes nothing."""
        advance = self.clock.check(t)
        u = np.clip(self.u_ff, self.gains.tension_min, self.gains.tension_max)
        if self.s_ref is None:
            return u
        u_ff = self.u_ff[self.active] if self.feedforward else np.zeros(len(self.active))
        now = float(t) if self.clock.time is None else self.clock.time + advance.dt
        if self._rate_since is None:
            self._rate_since = now
        rate = self.s_ref_dot if now - self._rate_since <= self.rate_hold else None
        out = self.pid.update(t, s, s_dot, self.s_ref, u_ff, rate)
        u[self.active] = out[self.active]
        return u


def tendon_controller_for(n_tendons: int, control, active, actuation_map: ActuationMap
                          ) -> TendonController:
    """The inner loop the controller configuration (``control.yaml``) describes, regulating the
    tendons ``active`` (0-based)."""
    gains = InnerLoopGains(np.array(control.proportional), np.array(control.derivative),
                           np.array(control.integral), control.integral_saturation,
                           control.tension_min, control.tension_max, control.tension_rate_limit)
    return TendonController(n_tendons, gains, actuation_map, active, control.feedforward,
                            reference_rate_hold(control), control.inner_loop_max_time_step)


def reference_rate_hold(control) -> float:
    """How long [s] a moving reference's rate counts after it arrived: three online CLIK periods
    (a reference is due every period; a late or lost frame is not a stop)."""
    return 3.0 / control.clik_rate
