"""Another tool's recording (a `ros2 bag record` of the bridge's topics): a channel of a type no reader here decodes
(sensor_msgs/JointState, which ros2-publish itself sends; /rosout in any `-a` bag) made `teletouch plot` and
read_signals refuse the whole file; a bag of raw bgr8 sensor_msgs/Image was "the recording has no images" to
iter_images (and to the replay sensor)."""

from __future__ import annotations

import numpy as np
import pytest

from teletouch.cli import main as cli_main
from teletouch.recording import image_msg, iter_images, read_signals, ros2msg_definition

T0 = 1_700_000_000_000_000_000


def _bag(path, image: bool) -> None:
    from geometry_msgs.msg import WrenchStamped
    from mcap.writer import Writer
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    topics = [("/teletouch/force", "geometry_msgs/msg/WrenchStamped"),
              ("/teletouch/joint_states", "sensor_msgs/msg/JointState")]
    if image:
        topics.append(("/teletouch/image", "sensor_msgs/msg/Image"))
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="rosbag2")
        ids = {}
        for topic, typ in topics:
            sid = w.register_schema(typ, "ros2msg", ros2msg_definition(typ).encode())
            ids[topic] = w.register_channel(topic, "cdr", sid, {})
        # a type no reader here decodes (in any `ros2 bag record -a`); its bytes are never looked at
        sid = w.register_schema("rcl_interfaces/msg/Log", "ros2msg", b"")
        ids["/rosout"] = w.register_channel("/rosout", "cdr", sid, {})
        for i in range(10):
            ns = T0 + i * 16_666_667
            m = WrenchStamped()
            m.header.frame_id = "digit"
            m.header.stamp.sec, m.header.stamp.nanosec = ns // 10**9, ns % 10**9
            m.wrench.force.z = 0.1 * i
            w.add_message(ids["/teletouch/force"], log_time=ns, publish_time=ns, data=serialize_message(m))
            j = JointState()
            j.header.stamp = m.header.stamp
            j.name, j.position = ["gripper"], [0.01 * i]
            w.add_message(ids["/teletouch/joint_states"], log_time=ns, publish_time=ns, data=serialize_message(j))
            w.add_message(ids["/rosout"], log_time=ns, publish_time=ns, data=b"\x00\x01\x00\x00log")
            if image:
                img = np.full((32, 24, 3), i, np.uint8)
                img[..., 2] = 200   # colour: B, G != R
                w.add_message(ids["/teletouch/image"], log_time=ns, publish_time=ns,
                              data=serialize_message(image_msg(img, ns * 1e-9, "digit")))
        w.finish()


def test_a_channel_of_an_unknown_type_is_left_out_not_the_whole_file(tmp_path, capsys):
    bag = tmp_path / "bag.mcap"
    _bag(bag, image=False)
    sig = read_signals(bag)   # before: RecordingError "no decoder for schema 'sensor_msgs/msg/JointState'"
    # (the JointState that ros2-publish sends is decoded now: tests/test_recording_jointstate.py)
    assert list(sig) == ["/teletouch/force", "/teletouch/joint_states.gripper.position"]
    ts, vs = sig["/teletouch/force"]
    assert len(ts) == 10 and ts[1] - ts[0] == pytest.approx(1 / 60, abs=1e-6)
    assert code_of(["plot", str(bag), "-o", str(tmp_path / "plots")]) == 0
    err = capsys.readouterr().err
    assert "not read (no decoder for their message types): /rosout (rcl_interfaces/msg/Log)" in err
    assert any((tmp_path / "plots").glob("*.png"))


def test_a_bag_of_raw_bgr8_images_gives_its_frames(tmp_path):
    bag = tmp_path / "bag.mcap"
    _bag(bag, image=True)
    frames = list(iter_images(bag))   # before: "the recording has no images"
    assert len(frames) == 10
    stamp, img = frames[3]
    assert img.shape == (32, 24, 3) and img.dtype == np.uint8 and img[0, 0].tolist() == [3, 3, 200]
    assert stamp == pytest.approx(3 / 60, abs=1e-6)


def code_of(argv: list[str]) -> int:
    return cli_main(argv)


# ---------------------------------------------------------------------------------------------- writing (review)
def test_two_node_ids_that_give_one_topic_are_refused(tmp_path):
    """'a-b' and 'a_b' are both valid node ids, and both became the MCAP topic /a_b/value, maybe of two types."""
    from teletouch.recording import Recorder, RecordingError
    from teletouch.testing import load_graph_text, make_registry

    spec = load_graph_text("clock: sim\nduration: 0.1\nnodes:\n  - {id: a-b, plugin: mock-sensor, rate: 10}\n"
                           "  - {id: a_b, plugin: mock-sensor, rate: 10}\n", "g.yaml", registry=make_registry())
    with pytest.raises(RecordingError, match=r"the ports a-b.value and a_b.value would share the topic /a_b/value"):
        Recorder(tmp_path / "r.mcap", spec, log=lambda m: None)


def test_a_wall_clock_recordings_epoch_is_graph_time_zero_not_the_first_steps_end(tmp_path):
    """The epoch (Unix time of graph time 0) was taken at the first tap, after a step, as if that step's time t
    were "now": every stamp was late by the first step's length (40 ms against ros2-publish's own stamps)."""
    import time

    from teletouch import Component, Kind, Port, hookimpl
    from teletouch.recording import Recorder
    from teletouch.runtime import Runtime
    from teletouch.testing import load_graph_text, make_registry

    seen: list[int] = []

    class Slow(Component):
        name = "slow-first-step"
        kind = Kind.SENSOR
        outputs = {"value": Port("float64", (), "N", "a value")}
        default_rate = 20.0

        def step(self, t, inputs):
            if not seen:
                seen.append(time.time_ns() - int(round(self.ctx.now() * 1e9)))   # graph time 0's Unix time
                time.sleep(0.06)
            return {"value": 1.0}

    class Plugin:
        @hookimpl
        def teletouch_components(self):
            return [Slow]

    spec = load_graph_text("clock: wall\nduration: 0.3\nnodes:\n  - {id: s, plugin: slow-first-step}\n", "g.yaml",
                           registry=make_registry(Plugin()))
    rt = Runtime(spec, log=lambda m: None)
    rec = Recorder(tmp_path / "r.mcap", spec, log=lambda m: None)
    rec.graph_now = rt.now
    rt.add_tap(rec.tap)
    res = rt.run()
    rec.close()
    assert res.status == "ok", res.message
    from teletouch.recording import open_recording

    recording, _ = open_recording(tmp_path / "r.mcap")
    # (a loaded machine may preempt between a clock read and the next: 30 ms; before: +60 ms, the first step)
    assert abs(recording.epoch_ns - seen[0]) < 30_000_000, (recording.epoch_ns - seen[0]) / 1e6
