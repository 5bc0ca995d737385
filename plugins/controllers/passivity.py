"""Time-domain passivity observer and controller (TDPA) for the leader port of a teleoperator. Pure functions.

Sign convention (the leader port of docs/ports.md): the force ``f`` the controller sends to the leader is positive
when it pushes the operator's fingers apart, the leader velocity ``v`` is positive when the gripper opens. The power
that flows *from the operator into the teleoperator* (controller + follower + environment + sensing) is therefore

    P_in = -f * v        (closing against a resisting force: P_in > 0, the network absorbs energy)

The **observer** integrates it, ``E(k) = E(k-1) + P_in(k) * dt``. A passive network never returns more energy than it
received, so ``E >= 0``; delays (a 30-60 Hz force estimate, the follower's servo lag) make the loop active and drive
``E`` negative. The **controller** (``position-force``'s default, ``passivity_controller: force``) then

1. adds a damping force ``-alpha * v``, ``alpha = -E_predicted / (v^2 dt)``, ``0 <= alpha <= max_damping`` (what the
   device can render; Omega.7: 40 N*s/m), raised and released smoothly;
2. cuts the feedback force towards zero, never past it, by what the capped damping leaves
   (:func:`reduce_force_to`, Ryu and Hannaford's force-limiting PC on the force path; less force is always safe) while
   the network pushes energy out and the leader moves faster than ``v_min`` (below it the energy is tiny, and cutting
   a standing deficit on every tremor makes the force chatter);
3. never turns the feedback force round and does nothing at all in free space: no drag, no pull on the fingers.

The energy is book-kept with the force that was really sent (after saturation and rate limits), so the observer
stays honest even when the controller cannot dissipate everything at once. ``passivity_controller: damping`` is the
classic TDPA (damping alone, which drags the hand in free space and pulls opening fingers).

**Two-port observer** (``position-force``'s default): :class:`FollowerPort` adds the follower port's energy, from the
force samples and the follower's opening at their capture times, so that the object's stored energy is neither
credited to the teleoperator nor forgotten by the leak below (with the leader port alone, the energy squeezed into
the object and forgotten reads as a deficit when it returns on release).

A positive energy reservoir lets an active loop run on energy the operator stored earlier (e.g. in a squeezed
object); ``leak_time`` makes the positive part of ``E`` decay with that time constant, so stored energy from long
ago cannot feed an oscillation. :func:`adapt_gain` (option) lowers the force scale while the cut keeps working.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

__all__ = ["PassivityState", "port_power", "observe", "damping_for", "passivity_force", "reduce_force_to",
           "adapt_gain", "commit", "FollowerPort", "same_sign", "opposite_signs"]


@dataclass
class PassivityState:
    """The observer's memory."""

    energy: float = 0.0        #: observed energy (J), including what the controller dissipated
    alpha: float = 0.0         #: damping applied in the last step (N*s/m)
    dissipated: float = 0.0    #: total energy dissipated by the controller (J)
    active_steps: int = 0      #: steps in which damping was injected (or the force was reduced)
    follower_energy: float = 0.0   #: two-port observer: energy the environment gave back at the follower port (J)


def same_sign(a: float, b: float) -> bool:
    """Both positive or both negative. Not ``a * b > 0``: the product of two tiny numbers underflows to 0 (a
    subnormal force estimate let the damping turn the feedback force round into a pull)."""
    return (a > 0.0 and b > 0.0) or (a < 0.0 and b < 0.0)


def opposite_signs(a: float, b: float) -> bool:
    """One positive, the other negative (see :func:`same_sign`)."""
    return (a > 0.0 and b < 0.0) or (a < 0.0 and b > 0.0)


def port_power(force: float, velocity: float) -> float:
    """Power (W) flowing from the operator into the teleoperator at the leader port."""
    return -force * velocity


def observe(energy: float, force: float, velocity: float, dt: float, leak_time: float | None = None) -> float:
    """One observer step: the energy after ``dt`` with ``force`` applied at ``velocity`` (leak on the positive part)."""
    e = energy
    if leak_time is not None and leak_time > 0 and e > 0:
        e *= math.exp(-dt / leak_time)
    return e + port_power(force, velocity) * dt


def damping_for(energy_pred: float, velocity: float, dt: float, max_damping: float, v_min: float = 1e-4) -> float:
    """The damping (N*s/m) that dissipates a negative predicted energy within one step, within [0, max_damping]."""
    if energy_pred >= 0.0 or dt <= 0.0 or abs(velocity) < v_min:
        return 0.0
    den = velocity * velocity * dt
    if den <= 0.0:                 # underflow: the damping would be unbounded
        return max_damping
    alpha = -energy_pred / den
    if not math.isfinite(alpha):
        return max_damping
    return min(alpha, max_damping)


def passivity_force(state: PassivityState, force: float, velocity: float, dt: float, max_damping: float,
                    leak_time: float | None = None, v_min: float = 1e-4,
                    reduce_force: bool = True, reduce_margin: float = 0.0) -> tuple[float, float]:
    """The force to send and the equivalent damping used (N*s/m); does not change ``state``.

    First a damping ``-alpha * v`` with ``alpha <= max_damping``; then, if ``reduce_force``, :func:`reduce_force_to`
    whatever deficit remains. The returned damping is the equivalent ``(force - sent) / v``, so it exceeds
    ``max_damping`` only through that reduction.
    Call :func:`commit` with the force finally sent (after saturation/rate limits) to advance the observer.
    """
    e_pred = observe(state.energy, force, velocity, dt, leak_time)
    alpha = damping_for(e_pred, velocity, dt, max_damping, v_min)
    out = force - alpha * velocity
    if reduce_force and alpha > 0.0:
        cut = reduce_force_to(out, e_pred + alpha * velocity * velocity * dt, velocity, dt, reduce_margin)
        if cut != out:
            out, alpha = cut, (force - cut) / velocity
    return out, alpha


def reduce_force_to(force: float, energy_after: float, velocity: float, dt: float, margin: float = 0.0,
                    v_min: float = 0.0, pay_time: float = 0.0) -> float:
    """Cut ``force`` towards zero (never past it) by the deficit that remains beyond ``margin`` (J) when the
    network is pushing energy out (``force * v > 0``, ``|v| >= v_min``); less force is always safe and the operator
    is never pulled. ``pay_time`` > ``dt`` spreads the payment of the deficit over that time (a smaller cut per
    step, no one-step click); 0 pays it within the step (the exact one-step TDPA)."""
    if energy_after + margin < 0.0 and same_sign(force, velocity) and dt > 0.0 and abs(velocity) >= v_min:
        span = abs(velocity) * max(dt, pay_time)
        # (a velocity so small that the product underflows to 0: the whole force goes, never a division by zero)
        cut = min(abs(force), -(energy_after + margin) / span) if span > 0.0 else abs(force)
        return force - math.copysign(cut, force)
    return force


def adapt_gain(gain: float, deficit_left: bool, dt: float, drop_rate: float = 2.0, recover_time: float = 1.0,
               min_gain: float = 0.1) -> float:
    """Scale (0..1] of the rendered feedback force. While a deficit remains that the capped damping could not
    dissipate, the scale drops by ``drop_rate`` per second (smoothly: no chatter, never a jump); otherwise it
    recovers towards 1 with the time constant ``recover_time``."""
    if deficit_left:
        gain -= drop_rate * dt
    else:
        gain += (1.0 - gain) * min(1.0, dt / recover_time)
    return min(1.0, max(min_gain, gain))


def commit(state: PassivityState, force_sent: float, force_undamped: float, velocity: float, dt: float,
           alpha: float, leak_time: float | None = None) -> PassivityState:
    """Advance the observer with the force really sent; records the dissipated part. Returns ``state``."""
    state.energy = observe(state.energy, force_sent, velocity, dt, leak_time)
    state.alpha = alpha
    if alpha > 0.0:
        state.active_steps += 1
        # energy absorbed by the damping part of what was sent (may be less than alpha*v^2*dt after limits)
        state.dissipated += max(0.0, port_power(force_sent - force_undamped, velocity) * dt)
    return state


class FollowerPort:
    """Two-port observer: the energy that crosses the follower port, from the force samples and the follower's
    opening at their capture times.

    The sensed force arrives late (a camera frame and the estimator); multiplying it by the follower's present
    velocity would misplace the energy in time, so the last ``size`` openings are kept (256: 0.26 s at 1 kHz)
    and each new sample ``(stamp, f)`` adds ``(f_prev + f) / 2 * (x_f(stamp) - x_f(stamp_prev)) / scale``: the
    energy the environment, seen through the force scale (``f`` is the leader-equivalent force) and the position
    scale, gave into the teleoperator between the two captures (opening while pushed apart: positive; squeezing:
    negative). With ideal, undelayed coupling this cancels the leader port's energy exactly, so the observer sees
    only what the teleoperator itself (delay, hold, servo lag) generates or stores, and the environment's stored
    energy is neither credited to it nor forgotten.
    """

    __slots__ = ("hist", "prev")

    def __init__(self, size: int = 256):
        self.hist: deque[tuple[float, float]] = deque(maxlen=size)     # (time, opening), oldest first
        self.prev: tuple[float, float] | None = None     # (force, opening) at the last sample's capture

    def record(self, t: float, x: float) -> None:
        """Keep the follower opening ``x`` at time ``t`` (call every controller step with a fresh reading)."""
        h = self.hist
        if not h or t > h[-1][0]:
            h.append((t, x))

    def opening_at(self, t: float) -> float | None:
        """The follower opening at time ``t`` (linear interpolation), or None when ``t`` is not covered."""
        h = self.hist
        if not h:
            return None
        t1, x1 = h[-1]
        if t >= t1:
            return x1 if t - t1 <= 0.005 else None
        for t0, x0 in reversed(h):
            if t0 <= t:
                return x0 + (x1 - x0) * (t - t0) / (t1 - t0)
            t1, x1 = t0, x0
        return None

    def sample(self, stamp: float, force: float, scale: float) -> float:
        """Energy (J) the environment gave into the teleoperator since the last sample; 0 when it cannot be told."""
        x = self.opening_at(stamp)
        if x is None or not math.isfinite(force):
            self.prev = None
            return 0.0
        prev, self.prev = self.prev, (force, x)
        if prev is None:
            return 0.0
        return 0.5 * (prev[0] + force) * (x - prev[1]) / scale

    def forget(self) -> None:
        """A gap in the force samples: the next one starts a new interval."""
        self.prev = None
