"""position-force's passivity controller when the capped damping would turn the feedback force round: with
``passivity_no_reversal`` (the default) the force stops at 0 N, so the energy cut may count on the damping only down
to zero force, not on the pull it never sends, and the ``damping`` it reports is the damping the hand got."""

from __future__ import annotations

import pytest

from teletouch import Sample
from teletouch.plugins.controllers.position_force import PositionForce
from teletouch.testing import Harness

# exact figures: no ramps of the estimate or the force, the leader port only, no prediction
P = {"deadband": 0.0, "force_prediction": False, "smoothing_time": 0.0, "max_force_rate": 1e5,
     "passivity_observer": "leader-port", "energy_leak_time": None, "reduction_time": 0.0}
F, V, DT = 2.0, 0.1, 1e-3      # the contact force (N), the leader opening (m/s) against it, the step (s)


def harness(extra: dict | None = None) -> Harness:
    return Harness(PositionForce, {**P, **(extra or {})})


def _in_contact(h, energy: float) -> None:
    """2 N of contact, the hand still, then a deficit of ``energy`` (J) in the observer, no damping yet."""
    for k in range(100):
        h.step(k * DT, leader_opening=0.02, leader_velocity=0.0, force=Sample(F, k * DT))
    assert h.comp.out_force == pytest.approx(F) and h.comp.pas.alpha == 0.0
    h.comp.pas.energy = energy


def _opening(h, k: int = 0) -> dict[str, float]:
    t = 0.1 + k * DT
    return h.step(t, leader_opening=0.02 + V * (k + 1) * DT, leader_velocity=V, force=Sample(F, t))


def test_the_energy_cut_does_not_count_on_a_reversal_the_controller_never_sends():
    """A deficit of 50 uJ while the hand opens at 0.1 m/s against 2 N: the damping that pays it in one step, 25
    N*s/m (under the 40 cap), would send 2 - 2.5 = -0.5 N, a pull; the controller stops at 0 N, so even the capped
    damping leaves the 50 uJ, and the cut (reduction_time 0: within the step) takes 50 uJ / (0.1 m/s x 1 ms) = 0.5 N
    off the damped 1.5 N. The cut counted on the -0.5 N (energy after: 0) and cut nothing."""
    with harness() as h:
        _in_contact(h, -5e-5)
        out = _opening(h)
        damped = F - 25.0 * (DT / 0.005) * V          # the damping rises over damping_smoothing (5 ms): 5 N*s/m
        assert damped == pytest.approx(1.5)
        assert out["gripper_force"] == pytest.approx(damped - 0.5)
        assert out["damping"] == pytest.approx((F - out["gripper_force"]) / V)     # damping + cut, as one damping


def test_the_reported_damping_is_what_the_hand_got_when_the_force_stops_at_zero():
    """The damping rose past the point where it turns the force round (2 N / 0.1 m/s = 20 N*s/m); the force stopped
    at 0 N, but the damping output (and status) reported the damping that would have pulled, up to 40 N*s/m."""
    with harness({"reduction_min_velocity": 1.0}) as h:   # (no cut: the damping alone)
        _in_contact(h, -1.0)                          # a deficit the capped damping (40 N*s/m) cannot pay
        outs = [_opening(h, k) for k in range(40)]
        stopped = [o for o in outs if o["gripper_force"] == 0.0]
        assert stopped, [o["gripper_force"] for o in outs]
        for o in stopped:
            assert o["damping"] == pytest.approx(F / V)      # 20 N*s/m: all of the 2 N, none of the pull
        assert h.comp.status()["damping_n_s_per_m"] == pytest.approx(F / V)
