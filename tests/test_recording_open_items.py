"""Recording items left open by the audit: drop counts under concurrent taps, plot and iter_images read once."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from teletouch import recording
from teletouch.recording import Recorder, plot_recording, read_signals

from fakes.mcap_files import hold_writer


class _SlowLen(dict):
    """An outputs dict whose len() lets the other threads run (as a thread switch can at any moment): it widens the
    window between reading and writing a shared counter."""

    def __len__(self) -> int:
        time.sleep(0.001)
        return super().__len__()


def test_drop_counts_are_exact_when_several_node_threads_drop_at_once(tmp_path):
    # every tap is dropped (max_queue_bytes 1 B and an array waits behind a held writer: no array fits), from 8
    # threads at once, as on a wall clock where every node's thread taps
    rec = Recorder(tmp_path / "drops.mcap", None, max_queue_bytes=1, log=lambda m: None)
    stuck = hold_writer(rec)
    rec.tap("first", 0.0, {"a": np.zeros(4)})   # larger than max_queue_bytes, nothing waits: it goes in
    threads_n, taps_n = 8, 25
    go = threading.Barrier(threads_n)

    def node(k: int) -> None:
        go.wait()
        for i in range(taps_n):
            rec.tap(f"n{k}", i * 0.001, _SlowLen(a=np.zeros(4), b=np.ones(4)))

    threads = [threading.Thread(target=node, args=(k,)) for k in range(threads_n)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    stuck.release.set()
    rec.close()
    assert rec.messages == 2   # the held one and the first array
    assert rec.dropped == threads_n * taps_n * 2


def _mixed_recording(path: Path, n: int = 6) -> Path:
    with Recorder(path, None, log=lambda m: None) as rec:
        for k in range(n):
            rec.tap("cam", k * 0.01, {"image": np.full((8, 10, 3), 10 * k % 256, np.uint8)})
            rec.tap("est", k * 0.01 + 0.005, {"force": 0.5 * k, "depth_max": 1e-4 * k})
    return path


def _count_opens(monkeypatch, path: Path) -> list[str]:
    """The times the recording module opens ``path`` (each is one more read of the whole file)."""
    opened: list[str] = []

    def counting_open(file, *args, **kwargs):
        if str(file) == str(path):
            opened.append(str(file))
        return open(file, *args, **kwargs)

    monkeypatch.setattr(recording, "open", counting_open, raising=False)
    return opened


def test_read_signals_and_plot_read_the_recording_once(tmp_path, monkeypatch):
    path = _mixed_recording(tmp_path / "mixed.mcap")
    opened = _count_opens(monkeypatch, path)
    sig = read_signals(path)
    assert len(opened) == 1
    assert sorted(sig) == ["est.depth_max", "est.force"]   # images left out, as before
    ts, f = sig["est.force"]
    assert np.allclose(ts, [k * 0.01 + 0.005 for k in range(6)], atol=1e-9)
    assert np.allclose(f, [0.5 * k for k in range(6)])
    with_images = read_signals(path, images=True)
    assert len(opened) == 2 and [int(im[0, 0, 0]) for im in with_images["cam.image"][1]] == [0, 10, 20, 30, 40, 50]
    logs: list[str] = []
    files = plot_recording(path, tmp_path / "plots", log=logs.append)
    assert len(opened) == 3   # one more read for the plot (it was three)
    assert [f.name for f in files] == ["est.png"] and files[0].stat().st_size > 0 and logs == []


def test_plot_of_a_cut_recording_still_warns_once_with_one_read(tmp_path, monkeypatch):
    path = _mixed_recording(tmp_path / "mixed.mcap", n=40)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-200])   # summary and footer lost, as after a crash
    opened = _count_opens(monkeypatch, cut)
    logs: list[str] = []
    plot_recording(cut, tmp_path / "plots", log=logs.append)
    assert len(opened) == 1
    assert len(logs) == 1 and logs[0].startswith(f"warning: {cut}: the recording is")
