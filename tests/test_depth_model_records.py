"""Two records of the depth model that said less than the truth.

- `calibrate depth` without `--background` takes the per-pixel median of all the folder's images, no-contact frames
  and presses the labeller flags or that have no label among them; the model file recorded {"from": "presses", ...}.
  It now records {"from": "images"} with how many of them are labelled presses, no-contact frames and unlabelled.
- A model's header was kept per (path, device, inode, mtime, size): a replacement of the same size that kept mtime and
  inode (`cp -p` over it, a write then os.utime back) gave the old header. The key now holds a digest of the 'meta'
  entry's bytes too."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import zipfile

import numpy as np

from helpers_depth import qvga_fixture

from teletouch.plugins.estimators import depth_calibration as C
from teletouch.plugins.estimators import normal_model
from teletouch.plugins.estimators.normal_model import load_model

qvga = qvga_fixture()


def no_contact_first(ims):
    """The QVGA presses with the first one's image replaced by a frame without contact (the per-pixel median of the
    presses), for the tests that label it "no contact": the press it shows, trained as flat gel, raised the change
    threshold above every press, and a calibration in which no press reads any depth is refused."""
    return [(ims[0][0], C.median_background([im for _, im in ims])), *ims[1:]]


def _calibrate(ims, labels):
    return C.calibrate(ims, 0.003, 17150.0, labels=labels, epochs=1, progress=False, hidden=(8,), holdout=1)


def test_the_median_of_the_images_is_recorded_as_such_with_its_presses_and_no_contact_frames(qvga):
    ims, labs, _ = qvga
    labels = dict(labs)
    first = sorted(labels)[0]
    labels[first] = C.Label(first, None, None, None, "no contact: the gel at rest")
    ims = no_contact_first(ims)
    res = _calibrate(ims, labels)
    assert np.array_equal(res.background, C.median_background([im for _, im in ims]))   # over all 10 images
    assert res.model.training["background"] == {"from": "images", "frames": 10, "statistic": "per-pixel median",
                                                "presses": 9, "no_contact": 1, "unlabelled": 0}


def test_images_without_a_label_are_counted_in_the_median_s_record(qvga):
    ims, labs, _ = qvga
    labels = dict(labs)
    del labels[sorted(labels)[-1]]   # not trained on, but in the median all the same
    res = _calibrate(ims, labels)
    assert res.model.training["background"] == {"from": "images", "frames": 10, "statistic": "per-pixel median",
                                                "presses": 9, "no_contact": 0, "unlabelled": 1}


def test_a_model_file_with_the_old_record_still_loads(tmp_path):
    old = {"from": "presses", "frames": 6, "statistic": "per-pixel median"}
    m = dataclasses.replace(load_model("sim-digit-qvga"), training={"seed": 0, "background": old})
    path = m.save(tmp_path / "old.model")
    assert json.loads(str(np.load(path)["meta"]))["version"] == 1
    assert load_model(path).training["background"] == old


# --- the header cache -------------------------------------------------------------------------------------------

def _stored_model(meta: dict) -> bytes:
    """The packaged model's entries with this 'meta', in an uncompressed zip (its size follows the meta's length)."""
    src = normal_model.resolve_model("sim-digit-qvga")
    out = io.BytesIO()
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zout:
        for name in zin.namelist():
            data = zin.read(name)
            if name == "meta.npy":
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.array(json.dumps(meta, sort_keys=True)), allow_pickle=False)
                data = buf.getvalue()
            zout.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data)
    return out.getvalue()


def test_a_same_size_replacement_with_the_old_mtime_gives_the_new_header(tmp_path):
    meta = json.loads(str(np.load(normal_model.resolve_model("sim-digit-qvga"))["meta"]))
    a = _stored_model(meta)
    b = _stored_model({**meta, "rows": 640, "cols": 480})   # as many digits: the same size
    assert len(a) == len(b) and a != b
    path = tmp_path / "sensor.model"
    path.write_bytes(a)
    assert normal_model.model_image_shape(path) == (320, 240)
    st = path.stat()
    path.write_bytes(b)   # in place: the same inode
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    now = path.stat()
    assert (now.st_ino, now.st_size, now.st_mtime_ns) == (st.st_ino, st.st_size, st.st_mtime_ns)
    assert normal_model.model_image_shape(path) == (640, 480)
    path.write_bytes(a)   # and back
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert normal_model.model_image_shape(path) == (320, 240)


def test_an_unchanged_header_is_parsed_once(tmp_path, monkeypatch):
    path = tmp_path / "sensor.model"
    path.write_bytes(_stored_model({"format": normal_model.FORMAT, "version": normal_model.VERSION, "rows": 320,
                                    "cols": 240, "cached": "once"}))
    parsed: list[str] = []
    check = normal_model._check_meta

    def spy(name, entry):
        parsed.append(name)
        return check(name, entry)

    monkeypatch.setattr(normal_model, "_check_meta", spy)
    for _ in range(3):
        assert normal_model.model_image_shape(path) == (320, 240)
    assert parsed == [str(path)]
