"""`calibrate depth` with labels: a "no contact" frame (trained as flat gel) was listed among the presses "marked
uncertain or without a complete circle, not used", although it was trained on. The log now says which frames are
left out and which no-contact frames are trained as flat gel."""

from __future__ import annotations

from teletouch.plugins.estimators import depth_calibration as C

from helpers_depth import qvga_fixture

qvga = qvga_fixture()


def no_contact_first(ims):
    """The QVGA presses with the first one's image replaced by a frame without contact (the per-pixel median of the
    presses), for the tests that label it "no contact": the press it shows, trained as flat gel, raised the change
    threshold above every press, and a calibration in which no press reads any depth is refused."""
    return [(ims[0][0], C.median_background([im for _, im in ims])), *ims[1:]]


def test_a_no_contact_frame_is_said_to_be_trained_as_flat_gel_not_left_out(qvga):
    ims, labs, bg = qvga
    labels = dict(labs)
    first = sorted(labels)[0]
    labels[first] = C.Label(first, None, None, None, "no contact: the gel at rest")
    ims = no_contact_first(ims)
    assert labels[first].no_contact and labels[first].uncertain
    logs: list[str] = []
    res = C.calibrate(ims, 0.003, 17150.0, labels=labels, background=bg, epochs=1, progress=False, hidden=(8,),
                      log=logs.append)
    assert first in res.model.training["presses"]   # trained on (as flat gel)
    assert not any("not used" in m and first in m for m in logs), logs
    assert any(m.startswith(f"1 no-contact frame(s) trained as flat gel: {first}") for m in logs), logs


def test_the_background_s_log_counts_images_not_presses(qvga):
    # it said "per-pixel median of 10 presses" of a folder whose frames include a no-contact one
    ims, labs, _ = qvga
    labels = dict(labs)
    first = sorted(labels)[0]
    labels[first] = C.Label(first, None, None, None, "no contact: the gel at rest")
    ims = no_contact_first(ims)
    logs: list[str] = []
    C.calibrate(ims, 0.003, 17150.0, labels=labels, epochs=1, progress=False, hidden=(8,), log=logs.append)
    assert "background: per-pixel median of the 10 images" in logs, logs
    assert not any("presses" in m for m in logs if m.startswith("background:")), logs
