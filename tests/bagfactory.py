"""Bags written with rosbags' own writers (ROS 1 and ROS 2, sqlite3 and MCAP) for tests and
benchmarks: IMU, NavSatFix and small camera images with values derived from the index, so a
reader's output can be checked against rosbags' deserialisation of the same bytes."""

from __future__ import annotations

import io
import shutil
import struct
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ruamel.yaml import YAML

BagKind = Literal["ros1", "sqlite3", "mcap"]
TOPICS = {
    "/imu": "sensor_msgs/msg/Imu",
    "/gps": "sensor_msgs/msg/NavSatFix",
    "/camera/image_raw": "sensor_msgs/msg/Image",
}
START_NS = 1_700_000_000_000_000_000
"""November 2023 in nanoseconds since the epoch, as real recordings stamp their messages."""
PERIOD_NS = 10_000_000


def typestore_for(kind: BagKind) -> Any:
    return get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)


def _header(store: Any, index: int, t_ns: int, frame: str) -> Any:
    time = store.types["builtin_interfaces/msg/Time"]
    header = store.types["std_msgs/msg/Header"]
    stamp = time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)
    if "seq" in store.fielddefs["std_msgs/msg/Header"][1][0][0]:
        return header(seq=index, stamp=stamp, frame_id=frame)
    return header(stamp=stamp, frame_id=frame)


def imu(store: Any, index: int, t_ns: int) -> Any:
    vector = store.types["geometry_msgs/msg/Vector3"]
    quaternion = store.types["geometry_msgs/msg/Quaternion"]
    covariance = np.arange(9, dtype=np.float64) * 0.01
    return store.types["sensor_msgs/msg/Imu"](
        header=_header(store, index, t_ns, "imu_link"),
        orientation=quaternion(x=0.0, y=0.0, z=np.sin(index / 100), w=np.cos(index / 100)),
        orientation_covariance=covariance,
        angular_velocity=vector(x=0.01 * index, y=-0.5, z=1.25),
        angular_velocity_covariance=covariance,
        linear_acceleration=vector(x=0.1, y=0.2, z=9.81 + index % 7),
        linear_acceleration_covariance=covariance,
    )


def navsatfix(store: Any, index: int, t_ns: int) -> Any:
    status = store.types["sensor_msgs/msg/NavSatStatus"](status=index % 3 - 1, service=1)
    return store.types["sensor_msgs/msg/NavSatFix"](
        header=_header(store, index, t_ns, "gps"),
        status=status,
        latitude=48.137 + index * 1e-6,
        longitude=11.575 - index * 1e-6,
        altitude=519.5,
        position_covariance=np.array([1.5, 0, 0, 0, 1.5, 0, 0, 0, 4.0], dtype=np.float64),
        position_covariance_type=2,
    )


def image(
    store: Any,
    index: int,
    t_ns: int,
    width: int = 8,
    height: int = 6,
    pixels: np.ndarray | None = None,
) -> Any:
    """An rgb8 image; ``pixels`` (``height * width * 3`` bytes) default to ``index``'s pattern."""
    if pixels is None:
        pixels = (np.arange(width * height * 3, dtype=np.uint32) + index) % 256
    return store.types["sensor_msgs/msg/Image"](
        header=_header(store, index, t_ns, "camera"),
        height=height,
        width=width,
        encoding="rgb8",
        is_bigendian=0,
        step=width * 3,
        data=pixels.astype(np.uint8),
    )


def messages(
    store: Any, count: int, image_every: int = 10, start_ns: int = START_NS
) -> Iterator[tuple[str, int, Any]]:
    """``count`` messages: IMU mostly, a NavSatFix every 5th and an image every ``image_every``."""
    for index in range(count):
        t_ns = start_ns + index * PERIOD_NS
        if index % image_every == image_every - 1:
            yield "/camera/image_raw", t_ns, image(store, index, t_ns)
        elif index % 5 == 4:
            yield "/gps", t_ns, navsatfix(store, index, t_ns)
        else:
            yield "/imu", t_ns, imu(store, index, t_ns)


WIDTH, HEIGHT = 640, 480
FRAME_BYTES = WIDTH * HEIGHT * 3
CAMERA_HZ, IMU_HZ = 10, 200


def camera_run(store: Any, frames: int) -> Iterator[tuple[str, int, Any]]:
    """A camera recording: ``frames`` 640x480 rgb8 images at 10 Hz (each distinct: a gradient
    under sensor noise, 0.9 MB), IMU at 200 Hz and NavSatFix at 10 Hz, in time order."""
    rng = np.random.default_rng(15)
    rows, columns = np.indices((HEIGHT, WIDTH))
    gradient = np.stack([rows * 255 // HEIGHT, columns * 255 // WIDTH, (rows + columns) % 256], -1)
    base = gradient.astype(np.uint8).reshape(-1)
    per_frame = IMU_HZ // CAMERA_HZ
    for step in range(frames * per_frame):
        t_ns = START_NS + step * 1_000_000_000 // IMU_HZ
        yield "/imu", t_ns, imu(store, step, t_ns)
        if step % per_frame == 0:
            pixels = base + rng.integers(0, 24, FRAME_BYTES, dtype=np.uint8)
            frame = image(store, step, t_ns + 1, WIDTH, HEIGHT, pixels=pixels)
            yield "/camera/image_raw", t_ns + 1, frame
        elif step % per_frame == per_frame // 2:
            yield "/gps", t_ns + 1, navsatfix(store, step, t_ns + 1)


def write_bag(
    path: Path,
    kind: BagKind,
    count: int,
    *,
    image_every: int = 10,
    ros1_chunk_bytes: int = 1 << 20,
    start_ns: int = START_NS,
) -> Path:
    """Write ``count`` messages to a new bag at ``path`` (a ``.bag`` file or a ROS 2 directory)."""
    store = typestore_for(kind)
    stream = messages(store, count, image_every, start_ns)
    return write_messages(path, kind, store, stream, ros1_chunk_bytes=ros1_chunk_bytes)


def write_messages(
    path: Path,
    kind: BagKind,
    store: Any,
    stream: Iterable[tuple[str, int, Any]],
    *,
    ros1_chunk_bytes: int = 1 << 20,
) -> Path:
    """Write ``(topic, t_ns, message)`` of :data:`TOPICS`, built with ``store`` (the typestore
    of ``kind``), to a new bag at ``path``, one message in memory at a time."""
    if kind == "ros1":
        writer = Rosbag1Writer(path)
        writer.set_compression(Rosbag1Writer.CompressionFormat.LZ4)
        writer.chunk_threshold = ros1_chunk_bytes
        with writer:
            connections = {
                topic: writer.add_connection(topic, msgtype, typestore=store)
                for topic, msgtype in TOPICS.items()
            }
            for topic, t_ns, message in stream:
                raw = store.serialize_ros1(message, TOPICS[topic])
                writer.write(connections[topic], t_ns, raw)
        return path
    plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
    with Rosbag2Writer(path, version=9, storage_plugin=plugin) as writer2:
        connections = {
            topic: writer2.add_connection(topic, msgtype, typestore=store)
            for topic, msgtype in TOPICS.items()
        }
        for topic, t_ns, message in stream:
            writer2.write(connections[topic], t_ns, store.serialize_cdr(message, TOPICS[topic]))
    return path


def write_split_bag(
    path: Path,
    kind: Literal["sqlite3", "mcap"],
    count: int,
    parts: int,
    *,
    image_every: int = 10,
    start_ns: int = START_NS,
) -> Path:
    """A ROS 2 bag directory split into ``parts`` storage files, as rosbag2 writes one with
    ``--max-bag-duration``: the messages of :func:`messages` cut in consecutive runs, one
    storage file each, under one ``metadata.yaml`` listing every file.

    rosbags' writer does not split, so each part is a bag of its own whose storage file is
    moved into ``path`` and whose metadata is merged.
    """
    store = typestore_for(kind)
    every = list(messages(store, count, image_every, start_ns))
    path.mkdir()
    infos: list[dict[str, Any]] = []
    for part in range(parts):
        chunk = every[part * len(every) // parts : (part + 1) * len(every) // parts]
        scratch = path / f".part{part}"
        write_messages(scratch, kind, store, chunk)
        info = YAML(typ="safe").load((scratch / "metadata.yaml").read_text())
        infos.append(info["rosbag2_bagfile_information"])
        (stored,) = info["rosbag2_bagfile_information"]["relative_file_paths"]
        name = f"{path.name}_{part}{Path(stored).suffix}"
        (scratch / stored).rename(path / name)
        infos[-1]["files"][0]["path"] = name
        shutil.rmtree(scratch)
    (path / "metadata.yaml").write_text(_merged_metadata(infos))
    return path


def _merged_metadata(parts: list[dict[str, Any]]) -> str:
    """One ``metadata.yaml`` over the parts' own, counts summed per topic."""
    merged = dict(parts[0])
    files = [file for part in parts for file in part["files"]]
    merged["files"] = files
    merged["relative_file_paths"] = [file["path"] for file in files]
    merged["message_count"] = sum(part["message_count"] for part in parts)
    starts = [file["starting_time"]["nanoseconds_since_epoch"] for file in files]
    ends = [
        file["starting_time"]["nanoseconds_since_epoch"] + file["duration"]["nanoseconds"]
        for file in files
    ]
    merged["starting_time"] = {"nanoseconds_since_epoch": min(starts)}
    merged["duration"] = {"nanoseconds": max(ends) - min(starts)}
    topics: dict[str, dict[str, Any]] = {}
    for part in parts:
        for entry in part["topics_with_message_count"]:
            name = entry["topic_metadata"]["name"]
            known = topics.setdefault(name, {**entry, "message_count": 0})
            known["message_count"] += entry["message_count"]
    merged["topics_with_message_count"] = list(topics.values())
    text = io.StringIO()
    YAML(typ="safe").dump({"rosbag2_bagfile_information": merged}, text)
    return text.getvalue()


def write_mcap_bomb(path: Path, declared: int = 1 << 30) -> int:
    """An MCAP file of one zstd chunk of ``declared`` bytes (one unknown record of zeros), a
    few KiB on disk: the decompression bomb a bag reader must refuse. Returns the chunk's
    offset. Compressed a MiB at a time, so writing it never holds the whole."""
    from backports import zstd
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, DataEnd, Footer, Header

    compressor = zstd.ZstdCompressor()
    record = b"\x80" + (declared - 9).to_bytes(8, "little")
    parts = [compressor.compress(record)]
    zeros = bytes(1 << 20)
    left = declared - len(record)
    while left > 0:
        parts.append(compressor.compress(zeros[: min(left, len(zeros))]))
        left -= len(zeros)
    parts.append(compressor.flush())
    builder = RecordBuilder()
    Header(profile="ros2", library="bomb").write(builder)
    offset = len(b"\x89MCAP0\r\n") + builder.count
    chunk = Chunk("zstd", b"".join(parts), 0, 0, 0, declared)
    chunk.write(builder)
    DataEnd(0).write(builder)
    Footer(0, 0, 0).write(builder)
    path.write_bytes(b"\x89MCAP0\r\n" + builder.end() + b"\x89MCAP0\r\n")
    return offset


def write_ros1_big_chunk(path: Path, size: int) -> Path:
    """A ROS 1 bag (lz4) of one ``std_msgs/msg/String`` of ``size`` zeros, so one chunk that
    decompresses to a little more: a few hundred KiB on disk."""
    store = get_typestore(Stores.ROS1_NOETIC)
    writer = Rosbag1Writer(path)
    writer.set_compression(Rosbag1Writer.CompressionFormat.LZ4)
    with writer:
        connection = writer.add_connection("/big", "std_msgs/msg/String", typestore=store)
        text = store.types["std_msgs/msg/String"](data="\0" * size)
        writer.write(connection, START_NS, store.serialize_ros1(text, "std_msgs/msg/String"))
    return path


FLAGS = "flag_msgs/msg/Flags"
"""``int32 seq`` and ``std_msgs/Bool[] flags``: in ROS 1 a Python object of about 100 bytes
per byte of its message, 1.45 µs each to decode."""


def write_flags_bag(path: Path, flags: int, *, chatter: str | None = None) -> Path:
    """A ROS 1 bag of one ``/flags`` message (``seq`` 7 and ``flags`` Bools, at ``START_NS +
    1``), after a ``/chatter`` ``std_msgs/msg/String`` of ``chatter`` if given."""
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("int32 seq\nstd_msgs/Bool[] flags", FLAGS))
    string = "std_msgs/msg/String"
    with Rosbag1Writer(path) as writer:
        if chatter is not None:
            said = store.serialize_ros1(store.types[string](data=chatter), string)
            writer.write(writer.add_connection("/chatter", string, typestore=store), START_NS, said)
        flagged = writer.add_connection("/flags", FLAGS, typestore=store)
        writer.write(flagged, START_NS + 1, struct.pack("<iI", 7, flags) + b"\x01" * flags)
    return path


def fanout_store(width: int, levels: int, base: Stores = Stores.EMPTY) -> Any:
    """``base``'s types and ``fan_msgs/msg/Level0``: ``width`` fields of ``Level1``, each
    ``width`` of ``Level2`` and so on, ``Level{levels}`` holding ``width`` floats: ``levels +
    1`` short definitions whose draft would hold ``width ** (levels + 1)`` leaves."""
    store = get_typestore(base)
    for level in range(levels):
        fields = "\n".join(f"fan_msgs/Level{level + 1} f{n}" for n in range(width))
        store.register(get_types_from_msg(fields, f"fan_msgs/msg/Level{level}"))
    floats = "\n".join(f"float64 x{n}" for n in range(width))
    store.register(get_types_from_msg(floats, f"fan_msgs/msg/Level{levels}"))
    return store


def ros2_mcap(path: Path, *channels: tuple[str, str, str, bytes]) -> Path:
    """An MCAP of one CDR message on each ``(topic, type, definition, message)``."""
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start(profile="ros2", library="test")
        for time_ns, (topic, msgtype, definition, message) in enumerate(channels, 1):
            schema = writer.register_schema(msgtype, "ros2msg", definition.encode())
            channel = writer.register_channel(topic, "cdr", schema)
            writer.add_message(channel, time_ns, message, time_ns)
        writer.finish()
    return path
