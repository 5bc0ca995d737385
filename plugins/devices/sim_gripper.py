"""sim-gripper: a simulated parallel gripper (position servo) closing on an object, with a gel fingertip.

The servo tracks the (clamped, speed-limited) opening setpoint with a first-order response of the given bandwidth;
it pushes with the force ``min(max_effort, servo_stiffness * (opening - setpoint))`` when blocked. Between the
fingers sits an object of ``object_width``, rigid or compliant (``object_stiffness``) down to its solid core
(``object_core_width``, rigid from there). The penetration of the fingers into the object is shared in series by the
fingertip gel(s) and the object; the gel's force-indentation law
is sim-digit's (``teletouch.plugins.sensors.gel.gel_force``), so ``indentation`` wired into sim-digit makes the
simulated DIGIT see exactly the squeeze whose force the gripper reports. Deterministic under the sim clock.
The hold and the safe state (which command the measured opening) keep the fingers where they are and the grip as it
is, as a real servo does, and commands after a hold pick the servo up from the effort it held (see
:meth:`SimGripper.servo_target`).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Literal

from pydantic import Field, field_validator, model_validator

from teletouch import Port, Sample, hookimpl
from teletouch.units import Hertz, Meters, NewtonsPerMeter, Pascals, plausible_opening

from teletouch.plugins.sensors import gel as _gel  # numpy only

from .follower_common import FOLLOWER_OUTPUTS, FollowerBase, FollowerParams, Reading, clamp
from .follower_contact import TabulatedGel, blocked_opening, split_penetration

DEFAULT_RADIUS = {"sphere": 0.003, "flat": 0.003, "probe": 0.005}  # sim-digit's defaults


def load_gel_law(p: Any) -> tuple[Callable[[float], float], Any]:
    """The fingertip gel's force law F(d): sim-digit's ``gel_force`` with the same indenter and gel parameters.

    It is the law's closed form with its constants computed once (``gel.force_law``, checked here against
    ``gel_force`` itself), wrapped with a table for the contact solvers when there is an object to squeeze.
    """
    gel = _gel
    radius = p.indenter_radius if p.indenter_radius is not None else DEFAULT_RADIUS[p.indenter]
    if p.indenter == "probe":
        indenter = gel.Indenter.probe(radius, p.tip_radius)
    elif p.indenter == "sphere":
        indenter = gel.Indenter.sphere(radius)
    else:
        indenter = gel.Indenter.flat(radius)
    material = gel.GelMaterial(p.modulus, p.poisson, p.gel_thickness)
    law = gel.force_law(indenter, material)
    reach = max(p.object_width or 0.0, p.max_opening)
    for k in range(41):  # the fast law is gel_force: same numbers (up to rounding) over the whole range
        d = reach * (k / 40.0) ** 2
        ref, fast = gel.gel_force(d, indenter, material), law(d)
        if not abs(fast - ref) <= 1e-12 * abs(ref):
            raise RuntimeError(f"gel.force_law disagrees with gel.gel_force at {d} m: {fast} N vs {ref} N")
    if p.object_width is None:
        return law, indenter
    return TabulatedGel(law, reach), indenter


class SimGripper(FollowerBase):
    """Simulated parallel gripper squeezing an object through a gel fingertip (contact, indentation, force)."""

    name = "sim-gripper"
    default_rate = 1000.0
    outputs = dict(FOLLOWER_OUTPUTS, **{
        "contact": Port("bool", (), "", "the fingers touch the object"),
        "indentation": Port("float64", (), "m", "how far the object presses into the fingertip gel (drives "
                                               "sim-digit's indentation input)"),
        "contact_force": Port("float64", (), "N", "ground-truth squeezing force"),
    })

    class Params(FollowerParams):
        initial_opening: Meters | None = Field(None, description="opening at start (None: max_opening)",
                                               json_schema_extra={"unit": "m"})
        bandwidth: Hertz = Field(10.0, gt=0, description="servo bandwidth (first-order)",
                                 json_schema_extra={"unit": "Hz"})
        servo_stiffness: NewtonsPerMeter = Field(4000.0, gt=0, description="force per metre of position error "
                                                 "when blocked (up to max_effort)", json_schema_extra={"unit": "N/m"})
        object_width: Meters | None = Field(0.04, gt=0, description="object between the fingers (None: no object); "
                                            "wider than min_opening and at most max_opening",
                                            json_schema_extra={"unit": "m"})
        object_stiffness: NewtonsPerMeter | None = Field(None, gt=0, description="object compliance in series "
                                                         "with the gel (None: rigid)",
                                                         json_schema_extra={"unit": "N/m"})
        object_core_width: Meters | None = Field(None, gt=0, description="width a compliant object cannot be "
                                                 "squeezed below (its solid core: rigid from there; None: half of "
                                                 "object_width); at most object_width",
                                                 json_schema_extra={"unit": "m"})
        # the gel, named and defaulted as sim-digit's parameters so that both nodes can share the same values
        indenter: Literal["sphere", "probe", "flat"] = Field("sphere", description="shape of the object's surface "
                                                             "where it presses into the gel (sim-digit's indenter)")
        indenter_radius: Meters | None = Field(None, gt=0, description="sphere/flat/probe radius (default 3 mm; "
                                               "probe 5 mm), as sim-digit", json_schema_extra={"unit": "m"})
        tip_radius: Meters = Field(0.010, gt=0, description="radius of the probe's curved tip",
                                   json_schema_extra={"unit": "m"})
        modulus: Pascals = Field(_gel.DEFAULT_MODULUS, gt=0, description="gel Young's modulus (Shore 10A ~0.41 MPa)",
                                 json_schema_extra={"unit": "Pa"})
        poisson: float = Field(0.5, ge=0, le=0.5, description="gel Poisson ratio")
        gel_thickness: Meters | None = Field(None, gt=0, description="gel layer thickness for the bonded "
                                             "thin-layer correction (None: half space)",
                                             json_schema_extra={"unit": "m"})
        gel_fingers: int = Field(1, ge=1, le=2, description="fingers with a gel pad (1: one DIGIT, the other rigid)")

        @field_validator("initial_opening", "object_width", "object_core_width")
        @classmethod
        def _opening(cls, v: float | None, info: Any) -> float | None:
            # before the range checks below: 20 meant 20 mm, not an opening 20 m wide
            return v if v is None else plausible_opening(info.field_name, v)

        @model_validator(mode="after")
        def _initial(self) -> "SimGripper.Params":
            _gel.check_gel_params(self)   # millimetres in metre fields, kPa/MPa as Pa: as sim-digit refuses them
            if self.initial_opening is not None and not (self.min_opening <= self.initial_opening
                                                         <= self.max_opening):
                raise ValueError(f"initial_opening {self.initial_opening} m is outside "
                                 f"[{self.min_opening}, {self.max_opening}] m")
            w = self.object_width
            if w is not None and w > self.max_opening:
                raise ValueError(f"object_width ({w * 1e3:g} mm) is wider than max_opening "
                                 f"({self.max_opening * 1e3:g} mm): the object does not fit between the fingers; "
                                 f"expected an object_width up to max_opening (null: no object)")
            if w is not None and w <= self.min_opening:
                raise ValueError(f"object_width ({w * 1e3:g} mm) is not wider than min_opening "
                                 f"({self.min_opening * 1e3:g} mm): the fingers could never touch it; expected an "
                                 f"object_width above min_opening (null: no object)")
            core = self.object_core_width
            if core is not None and w is None:
                raise ValueError(f"object_core_width ({core * 1e3:g} mm) is set without an object (object_width "
                                 f"is null): expected object_core_width null, or an object_width")
            if core is not None and core > w:
                raise ValueError(f"object_core_width ({core * 1e3:g} mm) is wider than object_width "
                                 f"({w * 1e3:g} mm): expected the object's solid core inside it, at most "
                                 f"object_width")
            return self

        def max_compression(self) -> float | None:
            """How far (m) a compliant object can be squeezed before its core stops it (None: no object)."""
            w = self.object_width
            if w is None:
                return None
            return w - (0.5 * w if self.object_core_width is None else self.object_core_width)

    # hardware hooks: the simulated servo ----------------------------------------------------------------------
    def _hw_open(self) -> None:
        p = self.params
        self.gel, self.indenter = load_gel_law(p)
        self.max_compression = p.max_compression()
        x0 = p.max_opening if p.initial_opening is None else p.initial_opening
        self.target = x0
        if p.object_width is not None and x0 < p.object_width:
            # starting inside the object: the fingers rest where a servo commanded to initial_opening balances
            # the contact force (never more than max_effort), as they would after closing there
            x0 = blocked_opening(p.object_width, x0, p.servo_stiffness, p.max_effort, self.gel, p.gel_fingers,
                                 p.object_stiffness, self.max_compression)
        self.x = x0
        self.v = 0.0
        self.t_sim: float | None = None
        self.indentation = 0.0
        self.force = 0.0
        self._hold_effort: tuple[float, float] | None = None     # (the held opening, the effort when it began)
        self._resume_offset = 0.0   # m: what is left of the hold's target offset after commands resumed
        self._travel = 0.0          # m: how far the set-point may move this step (the base's speed limit)
        self._contact_at(x0)

    def activate(self) -> None:
        """The servo model starts from rest at the first step (as the base's set-point does): the fingers stood
        still while the node was inactive (nothing stepped them), and the graph's clock may start afresh (the time
        of the last run's last step made every step of a new run look like no time had passed)."""
        self.t_sim = None
        self.v = 0.0
        self.peak_force = 0.0       # N: the largest true squeezing force of the run (results())
        super().activate()

    def _hw_read(self) -> Reading:
        return Reading(self.x, self.v, self.force)

    def _hw_write(self, opening: float) -> None:
        self.target = opening

    # physics ---------------------------------------------------------------------------------------------------
    def _contact_at(self, x: float) -> None:
        p = self.params
        pen = (p.object_width - x) if p.object_width is not None else 0.0
        if pen > 0:
            self.indentation, self.force = split_penetration(pen, self.gel, p.gel_fingers, p.object_stiffness,
                                                             self.max_compression)
        else:
            self.indentation, self.force = 0.0, 0.0

    def servo_target(self) -> float:
        """Where the P-only servo model pulls: the set-point, offset during a hold (and the safe state's) by the
        effort the servo had when the hold began over ``servo_stiffness``. The hold commands the measured
        opening; a real servo keeps its effort there (its integral action, or a gearbox the object cannot
        back-drive) and the fingers stay put. This model needs a position error for an effort, so without the
        offset the object pushed the fingers open and the grip relaxed (0.39 -> 0.27 N and 0.07 mm wider on the
        probe, 16 -> 6.8 N and 1.7 mm wider squeezing at max_effort).

        When commands resume, the servo picks up from the effort it held: the offset is not dropped but bled off
        by as much as the set-point may move each step (``max_speed``, the base's speed limit), so the target is
        continuous. A command asking for the same squeeze keeps the held target exactly while the set-point walks
        from the held opening back to it (dropping the offset at once dipped the grip for 2-80 ms: 16 -> 6.8 N at
        max_effort, 0.39 -> 0.27 N on the probe); a lighter squeeze or an opening is reached at up to twice
        ``max_speed``. The open safe state keeps nothing."""
        k = self.params.servo_stiffness
        # the safe state decides alone: its open mode keeps nothing of a hold (a stale command's) before it
        holding = self.params.safe_mode == "hold" if self._safe else self._holding is not None
        if not holding:                         # following commands, or the safe state's open: no hold
            if self._safe:                      # open: release at once
                self._resume_offset = 0.0
            elif self._hold_effort is not None:  # a hold just ended: start from its offset
                self._resume_offset = self._hold_effort[1] / k
            self._hold_effort = None
            if self._resume_offset > 0.0:
                self._resume_offset = max(self._resume_offset - self._travel, 0.0)
                return self.target - self._resume_offset
            return self.target
        self._resume_offset = 0.0
        if self._hold_effort is None or self._hold_effort[0] != self._hold_at:
            self._hold_effort = (self._hold_at, self.force)
        return self.target - self._hold_effort[1] / k

    def advance(self, t: float) -> None:
        """Move the fingers from the last step's time to ``t`` towards the servo's target (:meth:`servo_target`)."""
        p = self.params
        if self.t_sim is None:
            self.t_sim = t
            return
        dt = t - self.t_sim
        if dt <= 0:
            return
        self.t_sim = t
        x = self.x
        target = self.servo_target()
        x_free = x + (target - x) * (1.0 - math.exp(-2.0 * math.pi * p.bandwidth * dt))
        x_free = clamp(x_free, x - p.max_speed * dt, x + p.max_speed * dt)
        w = p.object_width
        if w is not None and x_free < w:
            x_block = blocked_opening(w, target, p.servo_stiffness, p.max_effort, self.gel, p.gel_fingers,
                                      p.object_stiffness, self.max_compression)
            # quasi-static contact: the fingers go no further into the object than where the servo's force
            # balances the contact force (and are pushed back out to there if they are further in; with the
            # target outside the object, out to its surface: nothing holds them in)
            x_new = max(x_free, x_block)
        else:
            x_new = x_free
        self.v = (x_new - x) / dt
        self.x = x_new
        self._contact_at(x_new)

    def step(self, t: float, inputs: Any) -> dict[str, Any]:
        # how far command_target may move the set-point this step: max_speed over the time it counts
        last = self._last_t
        self._travel = 0.0 if last is None else self.params.max_speed * max(min(t - last, self._max_dt), 0.0)
        target = self.command_target(t, inputs)
        self._hw_write(target)
        self.advance(t)
        out = self.outputs_from(self.read_state(t), t)
        out["contact"] = Sample(self.force > 0.0, t)
        out["indentation"] = Sample(self.indentation, t)
        out["contact_force"] = Sample(self.force, t)
        self.peak_force = max(self.peak_force, self.force)
        return out

    def results(self) -> dict[str, Any]:
        """The simulation's truth beside what the controller sensed (its results' peak_force)."""
        return {"true_peak_force_n": getattr(self, "peak_force", 0.0)}

    def status(self) -> dict[str, Any]:
        d = super().status()
        d.update(indentation_m=getattr(self, "indentation", None), contact_force_n=getattr(self, "force", None))
        return d


@hookimpl
def teletouch_components():
    return [SimGripper]
