"""hid-leader, safety review 2: a report that the parser does not read (another report id, too short) is no
measurement. It made the driver output its default state as a fresh measurement (a DualSense in Bluetooth simple mode:
the opening fully open, fresh stamps, the trigger ignored), kept a silent pad's link "alive", and moved a SpaceMouse's
opening on at the last rate; and a generic pad's trigger at byte 0 of a report with an id read the id as the trigger."""

from __future__ import annotations

import hid
import pytest
from pydantic import ValidationError

from teletouch import HardwareError
from teletouch.plugins.devices import hid_leader as hl
from teletouch.testing import Harness
from tests.test_leader_hid import DS_USB, PULL, FakeHid, _raw_step, _value, info

# DualSense over Bluetooth before the host asks for its full reports: report 0x01 of 10 bytes (sticks, buttons, L2,
# R2 at the end: here R2 fully pressed), not the 64-byte USB layout; parse_dualsense does not read it
DS_BT_SIMPLE = bytes.fromhex("01 80 80 80 80 08 00 00 00 ff")
OTHER_ID = bytes.fromhex("17 64 00")   # a SpaceMouse report of an id parse_spacemouse does not read


@pytest.fixture
def fake_hid(monkeypatch):
    backend = FakeHid([])
    monkeypatch.setattr(hid, "enumerate", backend.enumerate)
    monkeypatch.setattr(hid, "device", backend.device)
    return backend


def test_unread_reports_are_no_measurement_and_fault_after_report_timeout(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x0CE6))
    with Harness(hl.HidLeader, {}) as h:
        t, period = 0.0, 0.004
        with pytest.raises(HardwareError) as ei:
            while t < 5.0:
                fake_hid.reports.append(DS_BT_SIMPLE)
                assert h.step(t) == {}   # no opening was measured: nothing is output (not max_opening)
                t += period
        assert 0.5 < t <= 0.5 + period + 1e-9
        msg = str(ei.value)
        assert "DualSense (054c:0ce6) sent no report it reads for 0.50" in msg
        assert "report(s) came in a layout the dualsense parser does not read (the last: id 0x01, 10 bytes)" in msg
        assert "link lost" not in msg
        assert h.comp.status()["ignored_reports"] == h.comp.status()["reports"] > 100


def test_unread_reports_after_a_good_one_keep_its_stamp_and_fault(fake_hid):
    fake_hid.devices.append(info(0x054C, 0x0CE6))
    with Harness(hl.HidLeader, {}) as h:
        fake_hid.reports.append(DS_USB)
        first = _raw_step(h, 0.0)
        t, period = 0.004, 0.004
        with pytest.raises(HardwareError, match="sent no report it reads for 0.50"):
            while t < 5.0:
                fake_hid.reports.append(DS_BT_SIMPLE)
                out = _raw_step(h, t)
                assert out["gripper_opening"].stamp == first["gripper_opening"].stamp   # the data is not fresher
                assert out["gripper_opening"].value == first["gripper_opening"].value
                t += period


def test_spacemouse_opening_does_not_move_on_with_unread_reports(fake_hid):
    fake_hid.devices.append(info(0x256F, 0xC62F))
    with Harness(hl.HidLeader, {"max_speed": "20mm/s", "dead_band": 0.1}) as h:
        fake_hid.reports.append(PULL)
        x = _value(_raw_step(h, 0.0)["gripper_opening"])
        t, period = 0.008, 0.008
        with pytest.raises(HardwareError, match="sent no report it reads for 0.50.* while its cap was deflected"):
            while t < 5.0:   # the cap's reports are gone; reports of another id still come
                fake_hid.reports.append(OTHER_ID)
                out = _raw_step(h, t)
                assert _value(out["gripper_opening"]) == x   # it moved on at the last rate
                t += period
        assert 0.5 < t <= 0.5 + period + 1e-9


def test_generic_trigger_and_button_cannot_be_the_report_id_byte():
    with pytest.raises(ValidationError, match="trigger_offset: byte 0 is the report id"):
        hl.HidLeader.Params(device="generic", report_id=3, trigger_offset=0)
    with pytest.raises(ValidationError, match="button_offset: byte 0 is the report id"):
        hl.HidLeader.Params(device="generic", report_id=3, trigger_offset=2, button_offset=0)
    assert hl.HidLeader.Params(device="generic", report_id=3, trigger_offset=1, button_offset=2).trigger_offset == 1
    assert hl.HidLeader.Params(device="generic", trigger_offset=0, button_offset=0).trigger_offset == 0   # no ids


def test_report_timeout_is_at_most_2_s():
    # before: 500 (meant as ms) was 500 s: a dead link noticed after 8 minutes, and a SpaceMouse's last rate applied
    # for that long at once when a report came back
    with pytest.raises(ValidationError, match="report_timeout"):
        hl.HidLeader.Params(device="dualsense", report_timeout=500)
    assert hl.HidLeader.Params(device="spacemouse", report_timeout="500ms").report_timeout == 0.5
    assert hl.HidLeader.Params(device="generic", report_timeout=2.0).report_timeout == 2.0
