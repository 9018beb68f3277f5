"""Reader of event arrays in ROS bags (ROS 1 ``.bag`` files, ROS 2 bag folders) through ``rosbags``.

Two message types carry events, both ``header, height, width, events[]`` with each event
``x, y, ts, polarity`` (``ts`` a ROS time, ``polarity`` a bool):

* ``dvs_msgs/EventArray`` of rpg_dvs_ros (DAVIS, DVS), also written by ESIM and most event datasets;
* ``prophesee_event_msgs/EventArray`` of the Prophesee ROS drivers.

``rosbags`` (pure Python, no ROS install) reads the bag and decodes the messages. A ROS 1 bag, and a
recent ROS 2 bag, carries its message definitions and those are used; for a ROS 2 bag without them
the definitions of rpg_dvs_ros / prophesee_ros_wrapper are registered here. One topic is read: the
``topic`` asked for, by default the first event topic in name order. Event times are the events'
own ``ts`` (seconds and nanoseconds, floored to µs), not the bag's record times; the sensor size is
the ``height`` and ``width`` of the topic's first message (``None`` when they are 0, which some
drivers send). Messages are decoded one at a time and regrouped into chunks, so a bag of any size
streams in bounded memory.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

import numpy as np
from rosbags import rosbag1, rosbag2
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

from evseg_torch.errors import ConfigError, ReaderError
from evseg_torch.io.packets import concatenate, regroup

EVENT_ARRAY_TYPES = ("dvs_msgs/msg/EventArray", "prophesee_event_msgs/msg/EventArray")

# The .msg definitions of rpg_dvs_ros and prophesee_ros_wrapper (both packages define the same two).
_EVENT_MSG = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
_EVENT_ARRAY_MSG = "std_msgs/Header header\nuint32 height\nuint32 width\n{package}/Event[] events\n"

_ROSBAGS_ERRORS = (
    AnyReaderError,
    rosbag1.ReaderError,
    rosbag2.ReaderError,
    SerdeError,
    TypesysError,
    struct.error,
)
_ROW = np.dtype([("sec", np.int64), ("nanosec", np.int64), ("x", np.int32), ("y", np.int32), ("p", np.uint8)])
_EVENTS = np.dtype([("t", np.int64), ("x", np.int32), ("y", np.int32), ("p", np.uint8)])


def read(path: Path, topic: str | None = None) -> np.ndarray:
    """All events of the topic, as a structured array (``t`` µs, ``x``, ``y``, ``p`` 0/1)."""
    return concatenate(_messages(path, topic), "the event topic")


def chunks(path: Path, chunk_size: int, topic: str | None = None) -> Iterator[np.ndarray]:
    """Consecutive blocks of at most ``chunk_size`` events, decoded a message at a time."""
    return regroup(_messages(path, topic), chunk_size)


def sensor_size(path: Path, topic: str | None = None) -> tuple[int, int] | None:
    """``(height, width)`` of the topic's first message; ``None`` when the bag leaves them 0."""
    with _rosbags_errors(), AnyReader([path], default_typestore=_typestore()) as reader:
        connections = _event_connections(reader, topic)
        for connection, _, raw in reader.messages(connections=connections):
            message = reader.deserialize(raw, connection.msgtype)
            size = int(message.height), int(message.width)
            return size if all(size) else None
    raise ReaderError(f"the event topic {connections[0].topic!r} holds no messages")


def _messages(path: Path, topic: str | None) -> Iterator[np.ndarray]:
    with _rosbags_errors(), AnyReader([path], default_typestore=_typestore()) as reader:
        for connection, _, raw in reader.messages(connections=_event_connections(reader, topic)):
            events = reader.deserialize(raw, connection.msgtype).events
            if len(events):
                yield _as_array(events)


def _as_array(events: list) -> np.ndarray:
    rows = np.fromiter(
        ((e.ts.sec, e.ts.nanosec, e.x, e.y, e.polarity) for e in events), dtype=_ROW, count=len(events)
    )
    out = np.empty(len(rows), dtype=_EVENTS)
    out["t"] = rows["sec"] * 1_000_000 + rows["nanosec"] // 1000
    out["x"], out["y"], out["p"] = rows["x"], rows["y"], rows["p"]
    return out


def _event_connections(reader: AnyReader, topic: str | None) -> list:
    by_topic = {}
    for connection in reader.connections:
        by_topic.setdefault(connection.topic, []).append(connection)
    events = sorted(t for t, conns in by_topic.items() if conns[0].msgtype in EVENT_ARRAY_TYPES)
    if topic is None:
        if not events:
            found = ", ".join(f"{t} ({c[0].msgtype})" for t, c in sorted(by_topic.items())) or "none"
            raise ReaderError(f"the bag holds no {' or '.join(EVENT_ARRAY_TYPES)} topic; its topics: {found}")
        topic = events[0]
    if topic not in by_topic:
        raise ConfigError(f"the bag has no topic {topic!r}; its event topics: {', '.join(events) or 'none'}")
    if topic not in events:
        raise ConfigError(
            f"topic {topic!r} holds {by_topic[topic][0].msgtype}, not event arrays; "
            f"its event topics: {', '.join(events) or 'none'}"
        )
    return by_topic[topic]


@cache
def _typestore():
    """ROS 2's latest standard types plus the two event packages, for bags that carry no definitions."""
    store = get_typestore(Stores.LATEST)
    for package in ("dvs_msgs", "prophesee_event_msgs"):
        array = _EVENT_ARRAY_MSG.format(package=package)
        types = get_types_from_msg(_EVENT_MSG, f"{package}/msg/Event")
        types.update(get_types_from_msg(array, f"{package}/msg/EventArray"))
        store.register(types)
    return store


@contextmanager
def _rosbags_errors() -> Iterator[None]:
    """rosbags' exceptions derive from ``Exception`` alone; name them as an unreadable bag."""
    try:
        yield
    except _ROSBAGS_ERRORS as err:
        details = " ".join(str(err).split()) or "no details"
        raise ReaderError(f"cannot read the bag: {type(err).__name__}: {details}") from None
