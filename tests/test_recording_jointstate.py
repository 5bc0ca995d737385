"""A recording of the sensor_msgs/JointState that `ros2-publish` sends (a `ros2 bag record` of its joint_states topic)
was read without that channel: no reader here decoded JointState, so it was left out and named in
`Recording.undecoded` ("not read" in `teletouch plot`). It now reads back as one numeric signal per joint and field
(position, velocity, effort, as the message holds them: SI), at the messages' header stamps, and `teletouch plot`
draws them. A malformed message is an error naming the file, the channel and the message, as for the other types."""

from __future__ import annotations

import pytest

from teletouch.cli import main as cli_main
from teletouch.recording import RecordingError, open_recording, read_signals, ros2msg_definition

T0 = 1_700_000_000_000_000_000     # Unix ns of the bag's first message (its publish time): graph time 0
LATENCY = 3_000_000                # a bag's publish time is when the message was recorded, after its header stamp

# (header stamp offset ns, names, position, velocity, effort): as ros2-publish sends them, one message per
# measurement time with the fields measured then (the opening alone, then the three together), and a message of
# two joints, as another driver sends them
MESSAGES = [
    (10_000_000, ["gripper"], [0.010], [], []),
    (26_666_667, ["gripper"], [0.012], [0.125], [-1.5]),
    (43_333_333, ["gripper"], [], [0.25], []),
    (60_000_000, ["gripper", "wrist"], [0.014, 1.25], [0.0, -0.5], [2.0, 0.75]),
]


def _stamp(ns: int):
    from builtin_interfaces.msg import Time

    return Time(sec=ns // 10**9, nanosec=ns % 10**9)


def _bag(path, messages=MESSAGES, raw: dict[int, bytes] | None = None):
    """An MCAP file as rosbag2 writes one (profile ros2, ros2msg schemas, CDR from rclpy's own serializer): a force
    channel (its first message is the file's first: graph time 0) and /teletouch/joint_states. ``raw``: the bytes
    of some JointState messages (by index) instead of the serialized ones."""
    from geometry_msgs.msg import WrenchStamped
    from mcap.writer import Writer
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="rosbag2")
        ids = {}
        for topic, typ in (("/teletouch/force", "geometry_msgs/msg/WrenchStamped"),
                           ("/teletouch/joint_states", "sensor_msgs/msg/JointState")):
            sid = w.register_schema(typ, "ros2msg", ros2msg_definition(typ).encode())
            ids[topic] = w.register_channel(topic, "cdr", sid, {})
        m = WrenchStamped()
        m.header.stamp, m.header.frame_id = _stamp(T0), "digit"
        m.wrench.force.z = 0.5
        w.add_message(ids["/teletouch/force"], log_time=T0, publish_time=T0, data=serialize_message(m))
        for k, (dt, names, pos, vel, eff) in enumerate(messages):
            j = JointState()
            j.header.stamp, j.header.frame_id = _stamp(T0 + dt if dt is not None else 0), "digit"
            j.name, j.position, j.velocity, j.effort = names, pos, vel, eff
            data = (raw or {}).get(k, serialize_message(j))
            t = T0 + (dt or 0) + LATENCY
            w.add_message(ids["/teletouch/joint_states"], log_time=t, publish_time=t, data=data)
        w.finish()
    return path


def test_joint_states_read_back_as_a_signal_per_joint_and_field_at_their_header_stamps(tmp_path):
    bag = _bag(tmp_path / "bag.mcap")
    sig = read_signals(bag)
    key = "/teletouch/joint_states"
    assert sorted(sig) == ["/teletouch/force"] + sorted(f"{key}.{j}.{f}" for j, f in [
        ("gripper", "position"), ("gripper", "velocity"), ("gripper", "effort"),
        ("wrist", "position"), ("wrist", "velocity"), ("wrist", "effort")])

    def at(*ms):   # graph time (s) of header stamps given in ms after the bag's first message
        return pytest.approx([m * 1e-3 for m in ms], abs=1e-9)

    ts, vs = sig[f"{key}.gripper.position"]
    assert vs.dtype == float and vs.tolist() == [0.010, 0.012, 0.014] and ts.tolist() == at(10, 26.666667, 60)
    ts, vs = sig[f"{key}.gripper.velocity"]
    assert vs.tolist() == [0.125, 0.25, 0.0] and ts.tolist() == at(26.666667, 43.333333, 60)
    ts, vs = sig[f"{key}.gripper.effort"]
    assert vs.tolist() == [-1.5, 2.0] and ts.tolist() == at(26.666667, 60)
    for f, v in (("position", 1.25), ("velocity", -0.5), ("effort", 0.75)):
        ts, vs = sig[f"{key}.wrist.{f}"]
        assert vs.tolist() == [v] and ts.tolist() == at(60)
    # the other channel as before, on the same clock (graph time 0: the file's first message)
    ts, vs = sig["/teletouch/force"]
    assert ts.tolist() == [0.0] and vs.tolist() == [[0.0, 0.0, 0.5, 0.0, 0.0, 0.0]]


def test_open_recording_gives_each_message_by_joint_at_its_header_stamp(tmp_path):
    bag = _bag(tmp_path / "bag.mcap")
    rec, items = open_recording(bag)
    assert rec.undecoded == []   # before: ["/teletouch/joint_states (sensor_msgs/msg/JointState)"]
    joints = [(stamp, log, value) for key, stamp, log, value in items if key == "/teletouch/joint_states"]
    assert [v for _, _, v in joints] == [
        {"gripper": {"position": 0.010}},
        {"gripper": {"position": 0.012, "velocity": 0.125, "effort": -1.5}},
        {"gripper": {"velocity": 0.25}},
        {"gripper": {"position": 0.014, "velocity": 0.0, "effort": 2.0},
         "wrist": {"position": 1.25, "velocity": -0.5, "effort": 0.75}},
    ]
    for (stamp, log, _), (dt, *_rest) in zip(joints, MESSAGES):
        assert stamp == pytest.approx(dt * 1e-9, abs=1e-9)                 # the header stamp: the measurement
        assert log == pytest.approx((dt + LATENCY) * 1e-9, abs=1e-9)       # the bag's own time: its arrival


def test_a_message_without_a_header_stamp_is_at_its_publish_time(tmp_path):
    bag = _bag(tmp_path / "bag.mcap", messages=[(20_000_000, ["gripper"], [0.02], [], []),
                                                (None, ["gripper"], [0.03], [], [])])
    ts, vs = read_signals(bag)["/teletouch/joint_states.gripper.position"]
    assert vs.tolist() == [0.02, 0.03] and ts.tolist() == pytest.approx([0.020, LATENCY * 1e-9], abs=1e-9)


def test_teletouch_plot_draws_the_joints(tmp_path, capsys):
    bag = _bag(tmp_path / "bag.mcap")
    out = tmp_path / "plots"
    assert cli_main(["plot", str(bag), "-o", str(out)]) == 0
    captured = capsys.readouterr()
    assert "not read" not in captured.err, captured.err   # before: "not read (no decoder ...): /teletouch/joint_states"
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs == ["_teletouch_force.png", "_teletouch_joint_states.png"], pngs
    assert (out / "_teletouch_joint_states.png").stat().st_size > 1000
    # --select picks signals of one joint
    assert cli_main(["plot", str(bag), "-o", str(tmp_path / "wrist"), "--select", r"\.wrist\."]) == 0
    assert [p.name for p in (tmp_path / "wrist").glob("*.png")] == ["_teletouch_joint_states.png"]


@pytest.mark.parametrize("case", ["cut", "arrays"])
def test_a_malformed_joint_state_is_an_error_naming_the_file_channel_and_message(tmp_path, capsys, case):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    if case == "cut":   # the CDR cut short inside its names: rclpy's deserializer refuses it
        j = JointState()
        j.header.stamp, j.name, j.position = _stamp(T0 + 20_000_000), ["gripper"], [0.5]
        raw = {1: serialize_message(j)[:20]}
        why = r"RMWError: failed to deserialize ROS message"
    else:               # well-formed CDR, but 1 position for 2 joints: which joint's is it?
        raw = None
        why = (r"ValueError: 1 position values for 2 joint names \['gripper', 'wrist'\] \(each array must have one "
               r"value per name, or none\)")
    messages = [MESSAGES[0], (20_000_000, ["gripper", "wrist"], [0.5], [], [])]
    bag = _bag(tmp_path / f"{case}.mcap", messages=messages, raw=raw)
    head = (rf"{bag}: channel /teletouch/joint_states: message 2 \(at 0\.023 s\) cannot be decoded \(expected a CDR "
            rf"sensor_msgs/msg/JointState\): {why}")
    for read in (open_recording, read_signals):
        with pytest.raises(RecordingError, match=head):
            read(bag)
    assert cli_main(["plot", str(bag), "-o", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"teletouch plot: {bag}: channel /teletouch/joint_states: message 2"), err


def test_a_joint_named_twice_is_refused(tmp_path):
    bag = _bag(tmp_path / "twice.mcap", messages=[(20_000_000, ["gripper", "gripper"], [0.1, 0.2], [], [])])
    with pytest.raises(RecordingError, match=r"channel /teletouch/joint_states: message 1 \(at 0\.023 s\) cannot be "
                                             r"decoded .*: ValueError: joint 'gripper' is named twice"):
        read_signals(bag)
