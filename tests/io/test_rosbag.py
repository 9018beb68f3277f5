"""The ROS bag reader, on ROS 1 bags and ROS 2 bag folders written here by rosbags itself."""

import json
import tracemalloc

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from evseg_torch.app.cli import main
from evseg_torch.errors import ConfigError, ReaderError
from evseg_torch.io import iter_event_chunks, load_events, read_sensor_size, reader_for
from tests.helpers.io import HEIGHT, WIDTH, make_events, write_txt

DVS = "dvs_msgs/msg/EventArray"
PROPHESEE = "prophesee_event_msgs/msg/EventArray"

# The two packages' .msg files, as rpg_dvs_ros and prophesee_ros_wrapper define them.
_EVENT_MSG = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
_ARRAY_MSG = "std_msgs/Header header\nuint32 height\nuint32 width\n{}/Event[] events\n"


def _typestore(store):
    typestore = get_typestore(store)
    for package in ("dvs_msgs", "prophesee_event_msgs"):
        types = get_types_from_msg(_EVENT_MSG, f"{package}/msg/Event")
        types.update(get_types_from_msg(_ARRAY_MSG.format(package), f"{package}/msg/EventArray"))
        typestore.register(types)
    return typestore


ROS1, ROS2 = _typestore(Stores.ROS1_NOETIC), _typestore(Stores.ROS2_HUMBLE)


def _messages(typestore, events, msgtype, per_message, size):
    """``(record time ns, message)`` of event arrays of at most ``per_message`` events."""
    array = typestore.types[msgtype]
    event = typestore.types[msgtype.replace("EventArray", "Event")]
    stamp = typestore.types["builtin_interfaces/msg/Time"]
    header = typestore.types["std_msgs/msg/Header"]
    for begin in range(0, len(events), per_message):
        block = events[begin : begin + per_message]
        sec, usec = np.divmod(block["t"], 1_000_000)
        items = [
            event(x=int(x), y=int(y), ts=stamp(sec=int(s), nanosec=int(u) * 1000), polarity=bool(p > 0))
            for x, y, s, u, p in zip(block["x"], block["y"], sec, usec, block["p"], strict=True)
        ]
        fields = {"stamp": stamp(sec=int(sec[-1]), nanosec=int(usec[-1]) * 1000), "frame_id": ""}
        if "seq" in header.__dataclass_fields__:
            fields["seq"] = begin // per_message
        message = array(header=header(**fields), height=size[0], width=size[1], events=items)
        yield int(block["t"][-1]) * 1000, message


def write_ros1(path, topics, msgtype=DVS, per_message=100, size=(HEIGHT, WIDTH)):
    """A ROS 1 bag with one event topic per ``{topic: events}`` item, and a string topic ``/note``."""
    with Writer1(path) as writer:
        note = writer.add_connection("/note", "std_msgs/msg/String", typestore=ROS1)
        writer.write(note, 1, ROS1.serialize_ros1(ROS1.types["std_msgs/msg/String"](data="hi"), note.msgtype))
        for topic, events in topics.items():
            connection = writer.add_connection(topic, msgtype, typestore=ROS1)
            for time_ns, message in _messages(ROS1, events, msgtype, per_message, size):
                writer.write(connection, time_ns, ROS1.serialize_ros1(message, msgtype))
    return path


def write_ros2(path, events, msgtype=DVS, topic="/events"):
    with Writer2(path, version=9) as writer:
        connection = writer.add_connection(topic, msgtype, typestore=ROS2)
        for time_ns, message in _messages(ROS2, events, msgtype, 100, (HEIGHT, WIDTH)):
            writer.write(connection, time_ns, ROS2.serialize_cdr(message, msgtype))
    return path


@pytest.mark.parametrize("msgtype", [DVS, PROPHESEE])
def test_ros1_bag_equals_the_text_file_of_its_events(tmp_path, events, msgtype):
    bag = write_ros1(tmp_path / "a.bag", {"/dvs/events": events}, msgtype)
    write_txt(tmp_path / "a.txt", events)
    np.testing.assert_array_equal(load_events(bag), load_events(tmp_path / "a.txt"))
    assert read_sensor_size(bag) == (HEIGHT, WIDTH)
    chunks = list(iter_event_chunks(bag, chunk_size=130))
    assert [len(c) for c in chunks] == [130, 130, 130, 110]
    np.testing.assert_array_equal(np.concatenate(chunks), events)
    assert reader_for(bag) == "ROS bag"


def test_ros2_bag_folder(tmp_path, events):
    folder = write_ros2(tmp_path / "bag2", events)
    assert reader_for(folder) == "ROS bag"
    np.testing.assert_array_equal(load_events(folder), events)
    np.testing.assert_array_equal(np.concatenate(list(iter_event_chunks(folder, 64))), events)
    assert read_sensor_size(folder) == (HEIGHT, WIDTH)


def test_topic_option(tmp_path):
    first, second = make_events(n=50, seed=1), make_events(n=70, seed=2)
    bag = write_ros1(tmp_path / "a.bag", {"/right/events": second, "/left/events": first})
    np.testing.assert_array_equal(load_events(bag), first)  # the first event topic in name order
    np.testing.assert_array_equal(load_events(bag, topic="/right/events"), second)
    chunks = list(iter_event_chunks(bag, 30, topic="/right/events"))
    np.testing.assert_array_equal(np.concatenate(chunks), second)
    assert read_sensor_size(bag, topic="/right/events") == (HEIGHT, WIDTH)
    with pytest.raises(ConfigError, match=r"a\.bag: the bag has no topic '/nope'; its event topics: /left"):
        load_events(bag, topic="/nope")
    with pytest.raises(ConfigError, match="topic '/note' holds std_msgs/msg/String, not event arrays"):
        read_sensor_size(bag, topic="/note")


def test_topic_is_refused_for_other_formats(tmp_path, events):
    write_txt(tmp_path / "a.txt", events)
    with pytest.raises(ConfigError, match="topic applies to ROS bags only"):
        load_events(tmp_path / "a.txt", topic="/events")
    with pytest.raises(ConfigError, match="topic applies to ROS bags only"):
        iter_event_chunks(tmp_path / "a.txt", topic="/events")


def test_bag_without_event_topics(tmp_path):
    bag = write_ros1(tmp_path / "a.bag", {})
    with pytest.raises(ReaderError, match=r"no dvs_msgs/msg/EventArray or .* topic; its topics: /note"):
        load_events(bag)


def test_zero_height_and_width_mean_no_stored_size(tmp_path, events):
    bag = write_ros1(tmp_path / "a.bag", {"/events": events}, size=(0, 0))
    assert read_sensor_size(bag) is None
    np.testing.assert_array_equal(load_events(bag), events)


def test_corrupt_bag(tmp_path):
    path = tmp_path / "bad.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(ReaderError, match=r"bad\.bag: cannot read"):
        load_events(path)


@pytest.mark.slow
def test_a_million_events_stream_in_bounded_memory(tmp_path):
    # What is held: one bag chunk as read from disk (about 1 MB), one decoded message (rosbags makes two
    # Python objects per event, about 600 bytes) and the chunk being assembled; none grows with the bag.
    n, chunk_size = 1_000_000, 20_000
    events = make_events(n=n)
    bag = write_ros1(tmp_path / "big.bag", {"/events": events}, per_message=1_000)
    del events
    tracemalloc.start()
    try:
        count, last = 0, None
        for chunk in iter_event_chunks(bag, chunk_size):
            count += len(chunk)
            last = chunk["t"][-1]
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == n and last == make_events(n=n)["t"][-1]
    whole = n * 16  # the bag's events in canonical form; decoded as messages they take 40 times that
    assert peak < whole / 3, f"peak {peak / 2**20:.1f} MiB while streaming {whole / 2**20:.1f} MiB of events"


def test_cli_segments_the_chosen_topic(tmp_path):
    bag = write_ros1(tmp_path / "a.bag", {"/a": make_events(n=50, seed=1), "/b": make_events(n=3000, seed=2)})
    out = tmp_path / "out"
    assert (
        main(["--quiet", "segment", str(bag), "--out", str(out), "--topic", "/b", "--window-ms", "30"]) == 0
    )
    summary = json.loads((out / "a" / "summary.json").read_text())
    assert summary["events"] == 3000 and summary["sensor_size"] == [HEIGHT, WIDTH]
    assert main(["--quiet", "segment", str(bag), "--out", str(out), "--topic", "/nope", "--overwrite"]) == 2
