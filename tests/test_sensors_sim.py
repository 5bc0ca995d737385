"""sim-digit and its gel model: ground truth, rendering, ports, determinism, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from teletouch.errors import ModelFileError
from teletouch.plugins.sensors import gel, optics
from teletouch.plugins.sensors.gel import Indenter, gel_force, height_map
from teletouch.plugins.sensors.sim_digit import DigitSimulator, SimDigit
from teletouch.testing import Harness, make_registry, run_yaml

QV = gel.QVGA_M_PER_PX


def _radius_grid(shape, mpp, pos=(0.0, 0.0)):
    rows, cols = shape
    y = (np.arange(rows) - (rows - 1) / 2) * mpp - pos[1]
    x = (np.arange(cols) - (cols - 1) / 2) * mpp - pos[0]
    X, Y = np.meshgrid(x, y)
    return np.hypot(X, Y)


@pytest.mark.parametrize("R,d", [(0.003, 0.0005), (0.003, 0.0012), (0.005, 0.0015)])
def test_sphere_height_map_matches_analytic_cap(R, d):
    ball = Indenter.sphere(R)
    pos = (0.0011, -0.0023)
    shape = (320, 240)
    r = _radius_grid(shape, QV, pos)
    cap = np.maximum(d - (R - np.sqrt(np.maximum(R * R - r * r, 0))), 0) * (r < R)
    rigid = height_map(ball, d, pos, 0.0, shape, QV, deformation=False)
    assert rigid.dtype == np.float32 and rigid.shape == shape
    assert np.abs(rigid - cap).max() <= 0.01 * d
    # with the gel's deformation the surface still follows the cap wherever the gel touches the ball
    surf = gel.gel_surface(ball, d, pos, 0.0, shape, QV)
    m = surf.mask
    assert m.sum() > 100
    assert np.abs(surf.depth[m] - cap[m]).max() <= 0.01 * d
    assert abs(float(surf.depth.max()) - d) <= 0.01 * d
    # the contact patch is Hertz's: radius sqrt(R d)
    a_px = math.sqrt(m.sum() / math.pi) * QV
    assert a_px == pytest.approx(math.sqrt(R * d), rel=0.06)
    # around the contact the gel sags (less than at the edge of the contact), and is flat far away
    ring = (r > 1.1 * math.sqrt(R * d)) & (r < 1.4 * math.sqrt(R * d))
    assert (surf.depth[ring] > 0).all() and (surf.depth[ring] < d / 2 + 1e-9).all()
    assert (surf.depth[r > 3 * math.sqrt(R * d)] == 0).all()


def test_height_map_edge_cases():
    ball = Indenter.sphere(0.003)
    assert not height_map(ball, 0.0).any()
    assert not height_map(ball, -0.001).any()
    assert not height_map(ball, 0.001, (1.0, 1.0)).any()  # far outside the image
    with pytest.raises(ValueError, match="finite"):
        height_map(ball, float("nan"))
    with pytest.raises(ValueError, match="positive"):
        Indenter.sphere(-1.0)
    with pytest.raises(ValueError, match="tip radius"):
        Indenter.probe(0.005, 0.002)


@pytest.mark.parametrize("ind", [Indenter.sphere(0.003), Indenter.sphere(0.006), Indenter.probe(),
                                 Indenter.flat(0.003)])
def test_force_zero_at_zero_and_monotonic(ind):
    d = np.linspace(0, 0.002, 81)
    f = np.array([gel_force(x, ind) for x in d])
    assert f[0] == 0.0 and gel_force(-0.001, ind) == 0.0
    assert np.all(np.diff(f) > 0)
    assert np.isfinite(f).all()


def test_force_laws_and_realistic_magnitude():
    E = 0.5e6
    Es = E / (1 - 0.25)
    assert gel_force(0.001, Indenter.sphere(0.004), E) == pytest.approx(4 / 3 * Es * math.sqrt(0.004) * 0.001 ** 1.5)
    assert gel_force(0.001, Indenter.flat(0.002), E) == pytest.approx(2 * Es * 0.002 * 0.001)
    # stiffer gel, larger force; thin layer stiffer than a half space
    ball = Indenter.sphere(0.005)
    assert gel_force(0.001, ball, 1e6) > gel_force(0.001, ball, 0.5e6)
    assert gel_force(0.001, ball, thickness=0.0045) > gel_force(0.001, ball)
    # a DIGIT at 1-1.5 mm under a 5-6 mm radius indenter: a few newtons
    for ind in (Indenter.sphere(0.005), Indenter.sphere(0.006), Indenter.probe()):
        assert 1.0 < gel_force(0.001, ind) < gel_force(0.0015, ind) < 8.0
    assert gel.DEFAULT_MODULUS == pytest.approx(0.41e6, rel=0.02)  # Gent, Shore 10A


def test_probe_force_continuous_and_numeric_law_agrees():
    probe = Indenter.probe(0.005, 0.010)
    d1 = 0.005 ** 2 / 0.010
    below, above = gel_force(d1 * (1 - 1e-6), probe), gel_force(d1 * (1 + 1e-6), probe)
    assert above == pytest.approx(below, rel=1e-4)
    # the general law (used for user height maps) reproduces Hertz for a sampled sphere
    R, mpp = 0.003, 0.02e-3
    n = 301
    r = _radius_grid((n, n), mpp)
    surface = np.where(r < R, R - np.sqrt(np.maximum(R * R - r * r, 0)), np.inf)
    user = Indenter.from_height_map(surface, mpp)
    for d in (0.0005, 0.001):
        assert gel_force(d, user) == pytest.approx(gel_force(d, Indenter.sphere(R)), rel=0.05)
    hm = height_map(user, 0.001, (0, 0), 0.0, (320, 240), QV, deformation=False)
    ref = height_map(Indenter.sphere(R), 0.001, (0, 0), 0.0, (320, 240), QV, deformation=False)
    assert np.abs(hm - ref).max() < 0.05 * 0.001


def test_tilt_moves_the_deepest_point_of_a_flat_punch():
    punch = Indenter.flat(0.003)
    z0 = height_map(punch, 0.0005, (0, 0), 0.0, (320, 240), QV, deformation=False)
    zt = height_map(punch, 0.0005, (0, 0), 0.1, (320, 240), QV, deformation=False)
    # untilted: flat bottom; tilted: the deepest column is on the +x side and the footprint is smaller
    assert np.ptp(z0[z0 > 0]) < 1e-9
    deepest = np.unravel_index(np.argmax(zt), zt.shape)
    assert deepest[1] > 120 + 30
    assert 0 < (zt > 0).sum() < (z0 > 0).sum()
    assert gel_force(0.0005, punch, tilt_rad=0.1) < gel_force(0.0005, punch)


def test_package_data_is_shipped():
    assert optics.TABLE_FILE.is_file()
    t = optics.load_table()
    assert t.shape == (3, 125, 125, 6) and t.dtype == np.float32
    for res, shape in optics.RESOLUTIONS.items():
        bg = optics.load_background(res)
        assert bg.shape == (*shape, 3)
        assert 60 < bg.mean() < 160  # a real lit DIGIT frame, not black


def test_optical_table_matches_shared_original(shared_data):
    orig = np.load(shared_data / "digit-optical-model" / "polycalib.npz")
    t = optics.load_table()
    assert np.allclose(t[0], orig["grad_r"], rtol=1e-5, atol=1e-6)
    assert np.allclose(t[2], orig["grad_b"], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("res,shape", [("qvga", (320, 240)), ("vga", (640, 480))])
def test_sim_digit_ports_and_contact_location(res, shape):
    pos = (0.002, -0.003)
    with Harness(SimDigit, {"resolution": res, "indentation": "1mm", "position": "2mm, -3mm"}) as h:
        out = h.step(0.0)
        img = out["image"]
        assert img.dtype == np.uint8 and img.shape == (*shape, 3)
        assert out["gt_depth"].dtype == np.float32 and out["gt_depth"].shape == shape
        assert out["gt_contact_mask"].dtype == bool and out["gt_contact_mask"].shape == shape
        assert out["gt_max_depth"] == pytest.approx(0.001, rel=0.01)
        assert out["gt_force"] == pytest.approx(gel_force(0.001, Indenter.sphere(0.003)))
        bg = h.comp.sim.background_u8
        diff = np.abs(img.astype(int) - bg.astype(int)).sum(axis=2)
        assert diff.max() > 30
        # the change is centred on the indenter: x along columns, y along rows, from the image centre
        mpp = gel.QVGA_M_PER_PX if res == "qvga" else gel.VGA_M_PER_PX
        rows, cols = shape
        w = diff.astype(float) * (diff > 10)
        cy = (w.sum(axis=1) * np.arange(rows)).sum() / w.sum()
        cx = (w.sum(axis=0) * np.arange(cols)).sum() / w.sum()
        assert cx == pytest.approx((cols - 1) / 2 + pos[0] / mpp, abs=0.5e-3 / mpp)
        assert cy == pytest.approx((rows - 1) / 2 + pos[1] / mpp, abs=0.5e-3 / mpp)
        # no contact: exactly the background, zero ground truth
        out = h.step(0.1, indentation=0.0)
        assert np.array_equal(out["image"], bg)
        assert out["gt_force"] == 0.0 and out["gt_max_depth"] == 0.0 and not out["gt_contact_mask"].any()


def test_sim_digit_noise_drift_variation_deterministic():
    params = {"indentation": 0.0008, "noise": 2.0, "drift": 4.0, "drift_period": 1.0, "unit_variation": 1.0,
              "seed": 7}

    def frames(p):
        with Harness(SimDigit, p) as h:
            return [h.step(t)["image"] for t in (0.0, 0.1, 0.25, 0.5)]

    a, b = frames(params), frames(params)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)
    c = frames(dict(params, seed=8))
    assert not np.array_equal(a[0], c[0])
    # noise of about the requested size on top of the clean frame
    with Harness(SimDigit, {"noise": 2.0, "seed": 1}) as h:
        noisy = h.step(0.0)["image"].astype(float)
        clean = h.comp.sim.background_u8.astype(float)
        assert 1.5 < (noisy - clean).std() < 2.5
    # drift moves the global brightness over time
    with Harness(SimDigit, {"drift": 5.0, "drift_period": 1.0}) as h:
        means = [h.step(t)["image"].mean() for t in np.linspace(0, 1, 9)]
        assert np.ptp(means) > 6


def test_sim_digit_inputs_override_static_params_and_validate():
    with Harness(SimDigit, {"indentation": 0.0}) as h:
        out = h.step(0.0, indentation=0.001, position=np.array([0.0, 0.0]), tilt=0.0)
        assert out["gt_max_depth"] == pytest.approx(0.001, rel=0.01)
        with pytest.raises(ValueError, match="indentation must be finite"):
            h.step(0.1, indentation=float("nan"))
        with pytest.raises(ValueError, match="position"):
            h.step(0.2, indentation=0.001, position=np.array([0.0, np.inf]))


def test_sim_digit_param_errors(tmp_path):
    with pytest.raises(ValueError, match="position"):
        SimDigit.Params(position=[0.0, 0.0, 0.0])
    # units with or without a space, comma-separated; plain numbers may be space-separated
    for text in ("2 mm, -1 mm", "2mm,-1mm", "0.002 -0.001"):
        assert SimDigit.Params(position=text).position == pytest.approx((0.002, -0.001))
    with pytest.raises(ValueError, match="indenter_map"):
        with Harness(SimDigit, {"indenter": "map"}):
            pass
    bad = tmp_path / "bg.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(ModelFileError, match="bg.png"):
        with Harness(SimDigit, {"background": str(bad)}):
            pass
    with pytest.raises(ModelFileError, match="nothing.npz"):
        with Harness(SimDigit, {"optical_model": str(tmp_path / "nothing.npz")}):
            pass


def test_user_height_map_indenter(tmp_path):
    # a square stamp 2 mm wide with a flat face
    m = np.full((101, 101), np.inf)
    m[25:76, 25:76] = 0.0
    f = tmp_path / "stamp.npy"
    np.save(f, m)
    with Harness(SimDigit, {"indenter": "map", "indenter_map": str(f), "indenter_map_m_per_px": 0.04e-3,
                            "indentation": 0.0005}) as h:
        out = h.step(0.0)
        mask = out["gt_contact_mask"]
        area = mask.sum() * gel.QVGA_M_PER_PX ** 2
        assert area == pytest.approx(0.002 ** 2, rel=0.15)
        assert out["gt_force"] > 0


def test_sim_digit_in_a_graph_driven_by_a_ramp():
    reg = make_registry("teletouch.plugins.sensors.sim_digit")
    text = """
name: sim-digit-ramp
clock: sim
nodes:
  - id: press
    plugin: mock-sensor
    rate: 60
    params: {signal: ramp, amplitude: 0.004}
  - id: digit
    plugin: sim-digit
    rate: 30
    inputs: {indentation: press.value}
"""
    forces, depths = [], []

    def tap(node, t, outputs):
        if node == "digit":
            forces.append(outputs["gt_force"])
            depths.append(outputs["gt_max_depth"])

    run_yaml(text, reg, duration=0.3, taps=[tap])
    assert len(forces) >= 8
    forces = [f.value if hasattr(f, "value") else f for f in forces]
    assert forces[-1] > forces[len(forces) // 2] > 0
    assert np.all(np.diff(forces[1:]) >= 0)


def test_simulator_caches_a_resting_pose():
    sim = DigitSimulator()
    a, _ = sim.render(0.001)
    b, _ = sim.render(0.001)
    assert np.array_equal(a, b) and sim.renders == 1
    sim.render(0.0011)
    assert sim.renders == 2


@pytest.mark.parametrize("res", ["qvga", "vga"])
def test_radial_renderer_agrees_with_the_generic_2d_path(res):
    """The fast path (1-D profile, exact radial blur, analytic slopes, every 2nd pixel shaded) renders what the
    direct path (2-D blur of the depth map, central differences, every pixel) renders."""
    fast = DigitSimulator(res)
    slow = DigitSimulator(res, stride=1)
    slow.fast = False
    bg = fast.background_u8.astype(float)
    for d, pos, ind in ((0.0006, (0.0, 0.0), None), (0.0012, (0.002, -0.003), None),
                        (0.0011, (-0.001, 0.001), Indenter.probe())):
        if ind is not None:
            fast.indenter = slow.indenter = ind
        a = fast.render(d, pos)[0].astype(float) - bg
        b = slow.render(d, pos)[0].astype(float) - bg
        assert np.abs(b).max() > 30
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99
        assert np.abs(a - b).mean() < 0.5


def test_tilt_input_changes_the_image_of_a_flat_punch():
    with Harness(SimDigit, {"indenter": "flat", "indenter_radius": 0.002, "indentation": 0.0004}) as h:
        flat = h.step(0.0)
        tilted = h.step(0.1, tilt=0.08)
        assert tilted["gt_force"] < flat["gt_force"]
        assert tilted["gt_contact_mask"].sum() < flat["gt_contact_mask"].sum()
        bg = h.comp.sim.background_u8.astype(int)
        d0 = np.abs(flat["image"].astype(int) - bg).sum(axis=2)
        d1 = np.abs(tilted["image"].astype(int) - bg).sum(axis=2)
        cols = np.arange(d0.shape[1])

        def cx(w):
            return (w.sum(axis=0) * cols).sum() / w.sum()

        # the contact, the depth and the image response of the tilted punch move towards +x (its deepest edge)
        assert cx(tilted["gt_contact_mask"]) > cx(flat["gt_contact_mask"]) + 7
        assert cx(tilted["gt_depth"]) > cx(flat["gt_depth"]) + 7
        assert cx(d1) > cx(d0) + 5


def test_unit_variation_draws_a_different_sensor_per_seed():
    ref = DigitSimulator(unit_variation=0.0, seed=3).unit
    assert ref["response_gain"] == [1.0, 1.0, 1.0] and ref["blur_gain"] == 1.0
    a, b = DigitSimulator(unit_variation=1.0, seed=3), DigitSimulator(unit_variation=1.0, seed=4)
    assert a.unit != b.unit and DigitSimulator(unit_variation=1.0, seed=3).unit == a.unit
    ia, ib = a.render(0.001)[0].astype(float), b.render(0.001)[0].astype(float)
    assert np.abs(ia - ib).mean() > 1.0


def test_noise_is_fresh_every_frame():
    with Harness(SimDigit, {"noise": 3.0, "seed": 2, "indentation": 0.001}) as h:
        frames = [h.step(k / 60)["image"].astype(float) for k in range(4)]
    for a, b in zip(frames, frames[1:]):
        assert (a - b).std() == pytest.approx(3.0 * math.sqrt(2), rel=0.15)


def test_an_unreadable_indenter_map_is_refused_when_the_graph_is_validated(tmp_path):
    """`validate` said OK for indenter: map with no map, a missing one or a text file, and the run failed at start-up,
    passing on numpy's advice to load pickled data unsafely."""
    text = tmp_path / "hm.npy"
    text.write_text("hello world\n")
    pickled = tmp_path / "obj.npy"
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    flat = tmp_path / "flat.npy"
    np.save(flat, np.zeros(5))
    cases = [(None, r"indenter=map needs indenter_map"),
             (str(tmp_path / "nope.npy"), r"indenter_map '.*nope.npy' does not exist"),
             (str(tmp_path), r"is a folder"),
             (str(text), r"hm.npy': cannot read the height map \(.*\); expected a \.npy file"),
             (str(pickled), r"obj.npy': cannot read the height map \(it holds pickled \(object\) data\)"),
             (str(flat), r"flat.npy': indenter height map must be a 2-D array")]
    for path, msg in cases:
        with pytest.raises(ValueError, match=msg) as e:
            SimDigit.Params(indenter="map", indenter_map=path)
        assert "allow_pickle" not in str(e.value)
    good = tmp_path / "stamp.npy"
    np.save(good, np.zeros((5, 5)))
    assert SimDigit.Params(indenter="map", indenter_map=str(good)).indenter_map == str(good)
