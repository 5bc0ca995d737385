"""Open items from earlier reviews: gradient maps of different shapes on the torch Poisson solve, a NaN depth map from
the dense path's torch solve, the Harness's exit after a safe_state() error, a Dynamixel servo whose Current_Limit
is 0."""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fakes.dynamixel_emulator import DynamixelEmulator  # noqa: E402
from fakes.followers import packet_timeout_fixture  # noqa: E402
from helpers_depth import model_fixture, sim_fixture  # noqa: E402

from teletouch import Device, HardwareError, Port  # noqa: E402
from teletouch.plugins.devices.dynamixel_gripper import DynamixelGripper  # noqa: E402
from teletouch.plugins.estimators import poisson  # noqa: E402
from teletouch.plugins.estimators.depth_pipeline import DepthPipeline  # noqa: E402
from teletouch.testing import Harness  # noqa: E402


# --- 1. integrate_torch: gradient maps of different shapes -----------------------------------------------------------

@pytest.mark.parametrize("shx,shy", [((4, 4), (4, 1)), ((4, 1), (4, 4)), ((5, 5), (4, 4)), ((2, 6, 5), (6, 5)),
                                     ((6, 5), (3, 6, 5))])
def test_integrate_torch_refuses_gradient_maps_of_different_shapes(shx, shy):
    """gy (4, 1) against gx (4, 4) was broadcast: a (4, 4) depth from a column of slopes copied across, silently; a
    batch of gx against one gy map was solved as if gy were every frame's. integrate() refuses both."""
    gx, gy = torch.zeros(shx), torch.zeros(shy)
    with pytest.raises(ValueError, match=rf"gx and gy: expected gradient maps of one shape, got "
                                         rf"{re_shape(shx)} and {re_shape(shy)}"):
        poisson.integrate_torch(gx, gy)
    if len(shx) == len(shy) == 2:   # the numpy solver refuses the same maps
        with pytest.raises(ValueError):
            poisson.integrate(gx.numpy(), gy.numpy())


@pytest.mark.parametrize("shape", [(4, 1), (1, 4), (3, 1, 5), (4,)])
def test_integrate_torch_refuses_maps_under_2_x_2_as_integrate_does(shape):
    """A (4, 1) pair gave a (4, 1) depth; integrate() refuses a map under 2 x 2 (no interior to solve on)."""
    g = torch.zeros(shape)
    with pytest.raises(ValueError, match=r"gx: expected .*gradient maps? of at least 2 x 2, got shape"):
        poisson.integrate_torch(g, g.clone())
    if len(shape) == 2:
        with pytest.raises(ValueError, match=r"gx: expected a 2-D gradient map of at least 2 x 2"):
            poisson.integrate(g.numpy(), g.numpy())


def test_integrate_torch_still_solves_equal_shapes_single_and_batched():
    rng = np.random.default_rng(1)
    g = torch.from_numpy(rng.normal(0.0, 0.1, (2, 3, 12, 9)))
    z = poisson.integrate_torch(g[0], g[1])
    assert z.shape == (3, 12, 9) and torch.isfinite(z).all()
    ref = poisson.integrate(g[0, 1].numpy(), g[1, 1].numpy())
    assert np.allclose(poisson.integrate_torch(g[0, 1], g[1, 1]).numpy(), ref, atol=1e-9)
    assert np.allclose(z[1].numpy(), ref, atol=1e-9)


def re_shape(shape) -> str:
    return re.escape(str(tuple(shape)))


# --- 2. the dense path's torch solve refuses a depth that is not finite ---------------------------------------------

model = model_fixture()
sim = sim_fixture()


class _BadNormals(torch.nn.Module):
    """The model's network with non-finite normals on a few cells (a corrupt model in memory)."""

    def __init__(self, net, value: float):
        super().__init__()
        self.net, self.value = net, value

    def forward(self, f):
        out = self.net(f).clone()
        out[:, 10:12, 20:22, 0] = self.value
        return out


def _torch_solve_on_cpu(monkeypatch, pipe):
    """The dense path as on a GPU (integrate_torch) while the tensors stay on the CPU: the solver choice is made on
    the device type."""
    monkeypatch.setattr(pipe, "_torch_solve", True)
    calls = []
    real = poisson.integrate_torch

    def spy(gx, gy):
        calls.append(gx.shape)
        return real(gx, gy)

    monkeypatch.setattr(poisson, "integrate_torch", spy)
    return calls


@pytest.mark.parametrize("solve", ["torch", "cpu"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_dense_grid_depth_refuses_non_finite_normals_on_either_solver(model, sim, monkeypatch, solve, value):
    """On a GPU the dense path solved with integrate_torch, which gives a bad frame NaN: grid_depth returned a NaN
    depth map where the CPU solver (and the sparse path) raised. Now both raise integrate()'s error."""
    img = sim.render(0.8e-3, (0.0, 0.0), 0.0)[0]
    pipe = DepthPipeline(model, mode="dense")
    calls = _torch_solve_on_cpu(monkeypatch, pipe) if solve == "torch" else []
    clean = pipe.grid_depth(img)
    assert np.isfinite(clean).all() and clean.max() > 0.3e-3
    assert len(calls) == (1 if solve == "torch" else 0)
    pipe.net = _BadNormals(pipe.net, value)
    with pytest.raises(ValueError, match=r"gx: \d+ gradients are NaN or inf \(the first at row \d+, column \d+\)"):
        pipe.grid_depth(img)
    with pytest.raises(ValueError, match="NaN or inf"):
        pipe.max_depth(img)
    with pytest.raises(ValueError, match="NaN or inf"):
        pipe(img)


@pytest.mark.parametrize("solve", ["torch", "cpu"])
def test_dense_grid_depth_refuses_an_overflow_on_either_solver(model, sim, monkeypatch, solve):
    """Finite gradients whose depth overflows float32: integrate() names the cause; the torch solve gave NaN."""
    img = sim.render(0.8e-3, (0.0, 0.0), 0.0)[0]
    pipe = DepthPipeline(model, mode="dense")
    if solve == "torch":
        _torch_solve_on_cpu(monkeypatch, pipe)
    monkeypatch.setattr(pipe, "nz_min", 1e-38)   # a normal lying flat gives a slope of ~1e38

    class Flat(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, f):
            out = self.net(f).clone()
            out[:, 79:81, 59:61] = torch.tensor([1.0, 0.0, 0.0])   # in the contact (the grid's centre)
            return out

    pipe.net = Flat(pipe.net)
    with pytest.raises(ValueError, match="too large to integrate"):
        pipe.grid_depth(img)


def test_batch_depth_still_gives_nan_for_a_bad_frame(model, sim):
    img = sim.render(0.8e-3, (0.0, 0.0), 0.0)[0]
    pipe = DepthPipeline(model, mode="dense")
    pipe.net = _BadNormals(pipe.net, math.nan)
    z = pipe.batch_depth(np.stack([img, img]))
    assert torch.isnan(z).all()


# --- 3. Harness: deactivate() and close() after a safe_state() error -------------------------------------------------

def _device(calls, fail: set[str]):
    class Dev(Device):
        name = "flaky-device"
        outputs = {"y": Port("float64", (), "m")}

        def step(self, t, inputs):
            return {"y": 0.0}

    def method(what):
        def call(self):
            calls.append(what)
            if what in fail:
                raise OSError(f"{what} failed")
        return call

    for what in ("safe_state", "deactivate", "close"):
        setattr(Dev, what, method(what))
    return Dev


def test_harness_exit_deactivates_and_closes_after_a_safe_state_error_then_raises_it():
    """The runtime still deactivates and closes a device whose safe_state() raised; the Harness skipped
    deactivate()."""
    calls = []
    with pytest.raises(OSError, match="safe_state failed"):
        with Harness(_device(calls, {"safe_state"})) as h:
            h.step(0.0)
    assert calls == ["safe_state", "deactivate", "close"]


def test_harness_exit_after_a_safe_state_error_in_a_failing_body():
    calls = []
    with pytest.raises(OSError, match="safe_state failed") as info:
        with Harness(_device(calls, {"safe_state"})):
            raise KeyError("body")
    assert calls == ["safe_state", "deactivate", "close"]
    assert isinstance(info.value.__context__, KeyError)


def test_harness_exit_without_errors_is_unchanged():
    calls = []
    with Harness(_device(calls, set())):
        pass
    assert calls == ["safe_state", "deactivate", "close"]
    with pytest.raises(OSError, match="deactivate failed"):
        with Harness(_device(calls, {"deactivate"})):
            pass
    assert calls[3:] == ["safe_state", "deactivate", "close"]


# --- 4. dynamixel-gripper: Current_Limit 0 -----------------------------------------------------------------------

packet_timeout = packet_timeout_fixture(autouse=False)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("model_name,dxl_id,params", [
    ("xm430-w350", 15, {}),
    ("rh-p12-rn-a", 1, {"model": "rh-p12-rn-a", "ticks_open": 0, "ticks_closed": 740, "opening_at_ticks_open": 0.106,
                        "opening_at_ticks_closed": 0.0, "max_opening": 0.106, "newtons_per_amp": 100.0,
                        "max_effort": 30.0, "max_speed": 0.1}),
])
def test_a_servo_with_current_limit_0_is_refused_at_configure(packet_timeout, model_name, dxl_id, params):
    """Current_Limit 0 capped Goal_Current at 0: in current-based position mode the servo then has no torque and the
    gripper cannot grip at all; the start-up only logged it and went on."""
    with DynamixelEmulator(dxl_id, model_name, position=0) as emu:
        with emu._lock:
            emu._put(emu.table.current_limit, 0)
        h = Harness(DynamixelGripper, dict(params, port=emu.port, dxl_id=dxl_id, baudrate=1000000))
        addr = emu.table.current_limit[-2]
        with pytest.raises(HardwareError, match=rf"Current_Limit of Dynamixel ID {dxl_id} .* is 0: .*cannot grip.*"
                                                rf"set Current_Limit \(address {addr}\) in the servo's EEPROM with "
                                                rf"the Dynamixel Wizard"):
            with h:
                pass
        assert emu.get(emu.table.torque_enable) == 0   # nothing was started
        # a Current_Limit of 1 unit still starts (capped there, with its log line)
        with emu._lock:
            emu._put(emu.table.current_limit, 1)
        logs = []
        h = Harness(DynamixelGripper, dict(params, port=emu.port, dxl_id=dxl_id, baudrate=1000000))
        h.ctx._log = logs.append
        with h:
            assert emu.get(emu.table.goal_current) == 1
        assert any("Current_Limit 1" in m and "capped" in m for m in logs)
