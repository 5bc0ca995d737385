"""sim-digit open items: each node its own random stream (two fingers are two sensors), and the simulator itself
refuses the poses the node refuses (a contact off the gel, a tilt beyond 45 deg)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teletouch.testing import Harness, make_registry, run_yaml

from teletouch.plugins.sensors.sim_digit import DigitSimulator, SimDigit

NOISY = {"noise": 2.0, "indentation": 0.001}


def frames(params, node_id=None, n=3):
    h = Harness(SimDigit, params)
    if node_id is not None:
        h.comp.id = node_id          # as the runtime names a graph's node (node_id=<the node's id>)
    with h:
        return [h.step(k / 60)["image"].astype(np.float64) for k in range(n)]


def noise_corr(a, b):
    clean = DigitSimulator().render(0.001)[0].astype(np.float64)
    return float(np.corrcoef((a - clean).ravel(), (b - clean).ravel())[0, 1])


def test_two_nodes_of_one_graph_with_one_seed_draw_independent_noise():
    """Before: every sim-digit with the default seed drew the same noise (two fingers of one gripper: correlation
    1.0, unlike two real sensors)."""
    left, right = frames(NOISY, "left_digit"), frames(NOISY, "right_digit")
    assert abs(noise_corr(left[0], right[0])) < 0.02
    assert not np.array_equal(left[1], right[1])
    # ... each reproducible: the stream is derived from (seed, node id), not from Python's per-process hash
    assert all(np.array_equal(x, y) for x, y in zip(left, frames(NOISY, "left_digit")))


def test_two_nodes_in_a_graph_differ_and_a_shared_unit_makes_them_one_sensor():
    reg = make_registry("teletouch.plugins.sensors.sim_digit")
    seen: dict[str, list] = {}

    def tap(node, t, outputs):
        img = outputs["image"]
        seen.setdefault(node, []).append(np.asarray(getattr(img, "value", img), np.float64))

    def run(extra_b: str) -> dict[str, list]:
        seen.clear()
        run_yaml(f"""
name: two-fingers
clock: sim
nodes:
  - id: finger_a
    plugin: sim-digit
    rate: 30
    params: {{indentation: 1mm, noise: 2.0, unit_variation: 1.0}}
  - id: finger_b
    plugin: sim-digit
    rate: 30
    params: {{indentation: 1mm, noise: 2.0, unit_variation: 1.0{extra_b}}}
""", reg, duration=0.1, taps=[tap])
        return dict(seen)

    two = run("")
    # the pose rests: a frame minus the one before is the noise alone (whatever each unit's colours)
    da, db = (two[k][1] - two[k][0] for k in ("finger_a", "finger_b"))
    assert abs(float(np.corrcoef(da.ravel(), db.ravel())[0, 1])) < 0.02
    assert two["finger_a"][0].mean() != two["finger_b"][0].mean()  # and two units' colours (unit_variation)
    one = run(", unit: finger_a")     # finger_b simulates the same physical DIGIT as finger_a
    assert all(np.array_equal(x, y) for x, y in zip(one["finger_a"], one["finger_b"]))


def test_a_node_outside_a_graph_keeps_the_seeds_own_stream():
    """The defaults stay bit-identical: a node built outside a graph (its id is the component's name) and
    ``unit: sim-digit`` draw what DigitSimulator(seed=...) draws, as before."""
    sim = DigitSimulator(noise=2.0, seed=4)
    ref = [sim.render(0.001, t=k / 60)[0].astype(np.float64) for k in range(3)]
    for node_id, unit in ((None, None), ("sensor", "sim-digit")):
        got = frames(dict(NOISY, seed=4, **({"unit": unit} if unit else {})), node_id)
        assert all(np.array_equal(x, y) for x, y in zip(ref, got))
    assert not np.array_equal(frames(dict(NOISY, seed=4), "sensor")[0], ref[0])


def test_unit_must_be_a_name():
    with pytest.raises(ValueError, match="unit"):
        SimDigit.Params(unit="")


# --- the simulator refuses what the node refuses -------------------------------------------------------------------

@pytest.mark.parametrize("pos", [(0.02, 0.0), (0.0, -0.01), (-0.0071, 0.0)])
def test_the_simulator_refuses_a_contact_off_the_gel_with_the_nodes_message(pos):
    """Before: DigitSimulator.render drew an untouched image for a contact off the image (the node refused it)."""
    sim = DigitSimulator()
    with pytest.raises(ValueError, match="off the gel") as direct:
        sim.render(0.001, pos)
    with Harness(SimDigit, {"indentation": 0.001}) as h:
        with pytest.raises(ValueError, match="off the gel") as node:
            h.step(0.0, position=np.array(pos))
    assert str(direct.value) == str(node.value)
    # no contact: nothing to see, any position goes; on the edge: rendered
    sim.render(0.0, pos)
    sim.render(0.001, (0.0069, 0.0))


def test_the_simulator_refuses_a_tilt_beyond_45_degrees():
    sim = DigitSimulator(indenter=None)
    with pytest.raises(ValueError, match="45 deg"):
        sim.render(0.001, (0.0, 0.0), math.radians(50))
    with pytest.raises(ValueError, match="45 deg"):
        sim.render(0.0, (0.0, 0.0), 2.0)
    sim.render(0.001, (0.0, 0.0), math.radians(44))
