"""Reading bags: generated ROS 1 / ROS 2 bags and the real recordings in ../shared/data, against
rosbags' own reader; truncated, corrupt and undefined input."""

from __future__ import annotations

import json
import resource
import shutil
import struct
import sys
from collections import Counter
from collections.abc import Iterator
from itertools import islice
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from services.storage.bags import (
    MAX_CHUNK_BYTES,
    MAX_DEFINITION_BYTES,
    MAX_NAME,
    MAX_TOPICS,
    MAX_TYPE_DEPTH,
    MAX_UNROLLED,
    Bag,
    BagCorrupt,
    BagFormat,
    BagUnreadable,
    ChunkTooLarge,
    MessageUndecodable,
    MissingDefinition,
    hollow_array,
    inflate_declared,
    service_event_types,
)
from tests.bagfactory import (
    START_NS,
    TOPICS,
    BagKind,
    ros2_mcap,
    write_bag,
    write_mcap_bomb,
    write_ros1_big_chunk,
)
from tests.rosbags_compare import assert_matches_rosbags, decoded

DATA = Path(__file__).resolve().parents[5] / "shared" / "data"
MANIFEST = json.loads((DATA / "ros_manifest.json").read_text())


def generated(tmp_path: Path, kind: BagKind, count: int = 40) -> Path:
    name = "generated.bag" if kind == "ros1" else f"generated_{kind}"
    return write_bag(tmp_path / name, kind, count, ros1_chunk_bytes=16_384)


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_generated_bag_matches_rosbags(tmp_path: Path, kind: BagKind) -> None:
    path = generated(tmp_path, kind)
    with Bag.open(path) as bag:
        listed = {(c.topic, c.msgtype): c for c in bag.connections}
        messages = list(decoded(bag))
    assert set(listed) == set(TOPICS.items())
    assert {topic: c.count for (topic, _), c in listed.items()} == {
        "/imu": 32,
        "/gps": 4,
        "/camera/image_raw": 4,
    }
    imu = listed["/imu", "sensor_msgs/msg/Imu"]
    assert imu.definition_source == "bag"
    assert "geometry_msgs/Vector3 angular_velocity" in imu.definition.replace("msg/", "")
    assert [t_ns for _, t_ns, _ in messages] == [START_NS + i * 10_000_000 for i in range(40)]
    default = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    with AnyReader([path], default_typestore=default) as reader:
        expected = [
            (c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()
        ]
    assert len(expected) == len(messages)
    for (topic, t_ns, message), (their_topic, their_t_ns, original) in zip(
        messages, expected, strict=True
    ):
        assert (topic, t_ns) == (their_topic, their_t_ns)
        assert_matches_rosbags(message, original)
    image = next(message for topic, _, message in messages if topic == "/camera/image_raw")
    assert isinstance(image["data"], bytes)
    assert len(image["data"]) == 8 * 6 * 3


@pytest.mark.parametrize("entry", MANIFEST, ids=[entry["path"] for entry in MANIFEST])
def test_real_recordings_every_message_in_time_order(entry: dict[str, Any]) -> None:
    """Counts per topic as the recording's metadata reports them, including the bags rosbags'
    AnyReader reads as empty (QoS mismatch) or cannot open (service-event schemas)."""
    path = DATA / entry["path"]
    topics = entry["rosbags"].get("topics") or []
    with Bag.open(path) as bag:
        counts: Counter[str] = Counter()
        stamps = []
        for connection, t_ns, _ in bag.raw_messages():
            counts[connection.topic] += 1
            stamps.append(t_ns)
        listed = {c.topic: c for c in bag.connections}
    assert stamps == sorted(stamps)
    for topic in topics:
        assert counts[topic["topic"]] == topic["count_reported"], topic["topic"]
        assert listed[topic["topic"]].msgtype == topic["msgtype"]
    if entry["rosbags"].get("first_ts_ns") is not None:
        assert stamps[0] == entry["rosbags"]["first_ts_ns"]
        assert stamps[-1] == entry["rosbags"]["last_ts_ns"]
    if not topics:
        assert sum(counts.values()) == sum(info["message_count"] for info in entry["mcap"].values())


READABLE = [
    "rosbag1/robot_localization_test2.bag",
    "rosbag1/evo_tf_example.bag",
    "rosbag2/evo_tf_example",
    "rosbag2/robot_localization_ardrone_test3_sqlite3_zstd_file",
    "rosbag2/rosbag2_cdr_test_sqlite3",
    "mcap/robot_localization_test2_mcap",
    "mcap/cartographer_b0_short_mcap_zstd",
    "mcap/rosbag2_cdr_test_mcap",
    "mcap/rosbag2_cpp_only_topics.mcap",
]


@pytest.mark.parametrize("relative", READABLE)
def test_real_recordings_decode_as_rosbags_does(relative: str) -> None:
    path = DATA / relative
    with Bag.open(path) as bag:
        ours = list(islice(decoded(bag), 300))
    with AnyReader([path]) as reader:
        theirs = []
        for connection, t_ns, raw in reader.messages():
            theirs.append((connection.topic, t_ns, reader.deserialize(raw, connection.msgtype)))
            if len(theirs) == 300:
                break
    assert [(topic, t) for topic, t, _ in ours] == [(topic, t) for topic, t, _ in theirs]
    for (_, _, plain), (_, _, message) in zip(ours, theirs, strict=True):
        assert_matches_rosbags(plain, message)


@pytest.mark.parametrize("relative", ["rosbag2/rosbag2_wbag_sqlite3", "mcap/rosbag2_wbag_mcap"])
def test_split_bag_reads_every_file_in_time_order(relative: str) -> None:
    with Bag.open(DATA / relative) as bag:
        assert bag.format is BagFormat.ROS2_DIRECTORY
        messages = list(decoded(bag))
    stamps = [t_ns for _, t_ns, _ in messages]
    assert len(messages) == 6074
    assert stamps == sorted(stamps)
    assert (stamps[0], stamps[-1]) == (1000, 2998)
    assert Counter(topic for topic, _, _ in messages)["AAA"] == 804
    assert all(isinstance(message["data"], str) for _, _, message in messages)


def test_bag_without_definitions_falls_back_to_the_bundled_typestore() -> None:
    with Bag.open(DATA / "rosbag2/rosbag2_wbag_sqlite3") as bag:
        sources = {c.definition_source for c in bag.connections}
        definition = bag.connections[0].definition
    assert sources == {"ros2_humble"}
    assert definition.strip() == "string data"


@pytest.mark.parametrize("relative", ["rosbag2/rosbag2_talker_sqlite3", "mcap/rosbag2_talker_mcap"])
def test_talker_directory_yields_its_messages_despite_qos_mismatch(relative: str) -> None:
    with Bag.open(DATA / relative) as bag:
        strings = [message["data"] for _, _, message in decoded(bag, topics=["/topic"])]
    assert len(strings) == 10
    assert strings[0] == "Hello, world! 0"


def test_undecodable_message_names_topic_type_and_time() -> None:
    with (
        Bag.open(DATA / "rosbag2/rosbag2_talker_sqlite3") as bag,
        pytest.raises(MessageUndecodable) as caught,
    ):
        list(decoded(bag, topics=["/rosout"]))
    assert caught.value.topic == "/rosout"
    assert caught.value.msgtype == "rcl_interfaces/msg/Log"
    assert caught.value.t_ns > 0
    assert "size mismatch" in str(caught.value)


def test_one_unusable_definition_disables_only_its_topics() -> None:
    """The sqlite3 twin of the service-event bag carries no definition of its events, and
    rosbags' typestore has none: those topics alone cannot be decoded."""
    with Bag.open(DATA / "rosbag2/rosbag2_topics_and_service_events_sqlite3") as bag:
        problems = {c.topic: c.problem for c in bag.connections}
        good = list(decoded(bag, topics=["/test_topic1", "/test_topic2"]))
        with pytest.raises(MissingDefinition) as caught:
            list(decoded(bag))
    assert problems["/test_topic1"] is None
    assert problems["/test_service1/_service_event"] is not None
    assert "test_msgs/srv/BasicTypes_Event" in problems["/test_service1/_service_event"]
    assert len(good) == 2
    assert caught.value.topic.startswith("/test_service")


def test_recorded_service_calls_decode_from_the_services_definition() -> None:
    """rosbag2 records a service's introspection events with the service's definition
    (``int64 a / int64 b / --- / int64 sum``) as their schema, which parses as no message:
    the calls were undecodable. Decoded as ROS 2's generated event type, the recording's
    three calls add up, each request and its response paired by sequence number, and every
    message's CDR is consumed exactly (rosbags checks its size)."""
    with Bag.open(DATA / "mcap/rosbag2_cpp_topics_and_services.mcap") as bag:
        problems = {c.topic: c.problem for c in bag.connections}
        events = [message for _, _, message in decoded(bag, ["/add_two_ints/_service_event"])]
    assert problems["/add_two_ints/_service_event"] is None
    requests = {e["info"]["sequence_number"]: e["request"] for e in events if e["request"]}
    responses = {e["info"]["sequence_number"]: e["response"] for e in events if e["response"]}
    assert requests == {1: [{"a": 1, "b": 3}], 2: [{"a": 2, "b": 3}], 3: [{"a": 3, "b": 3}]}
    assert {n: [{"sum": r[0]["a"] + r[0]["b"]}] for n, r in requests.items()} == responses
    received, sent = 1, 2  # service_msgs/msg/ServiceEventInfo REQUEST_RECEIVED, RESPONSE_SENT
    assert [e["info"]["event_type"] for e in events] == [received, sent] * 3
    assert {len(e["info"]["client_gid"]) for e in events} == {16}


def test_a_services_events_of_every_field_type_decode() -> None:
    """test_msgs' BasicTypes service (every primitive type, a string) as a client and a
    server recorded it: each call's request and response, by sequence number."""
    with Bag.open(DATA / "mcap/rosbag2_topics_and_service_events_mcap") as bag:
        events = [(topic, message) for topic, _, message in decoded(bag)]
    calls = Counter(
        (topic, e["info"]["sequence_number"], e["info"]["event_type"])
        for topic, e in events
        if topic.endswith("/_service_event")
    )
    sent, received = 0, 3  # REQUEST_SENT, RESPONSE_RECEIVED: the client's side
    assert calls == {
        (f"/test_service{n}/_service_event", call, kind): 1
        for n in (1, 2)
        for call in (1, 2)
        for kind in (sent, received)
    }
    request = next(e["request"][0] for _, e in events if e.get("request"))
    numbers = [f"{kind}{bits}_value" for bits in (8, 16, 32, 64) for kind in ("int", "uint")]
    expected = ["bool_value", "byte_value", "char_value", "float32_value", "float64_value"]
    assert sorted(request) == sorted([*expected, *numbers, "string_value"])


SEPARATOR = "=" * 80 + "\n"
GOOD_STRING = (
    "/ok",
    "std_msgs/msg/String",
    "string data\n",
    b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00",
)


def chained_types(count: int) -> str:
    """A definition of ``pkg/msg/T0`` holding ``T1``, which holds ``T2``... ``count`` types."""
    sections = [f"{SEPARATOR}MSG: pkg/T{n}\npkg/T{n + 1} next\n" for n in range(1, count - 1)]
    return "".join(["pkg/T1 next\n", *sections, f"{SEPARATOR}MSG: pkg/T{count - 1}\nint32 x\n"])


@pytest.mark.parametrize(
    ("definition", "cycle"),
    [
        ("pkg/Foo[] children\nint32 x\n", "pkg/msg/Foo -> pkg/msg/Foo"),
        (f"pkg/Bar bar\n{SEPARATOR}MSG: pkg/Bar\npkg/Foo[<=2] foo\n", "Foo -> pkg/msg/Bar -> "),
    ],
    ids=["itself", "through-another"],
)
def test_a_type_holding_itself_disables_only_its_topic(
    tmp_path: Path, definition: str, cycle: str
) -> None:
    """rosbags follows such a type without end: a 300-byte bag failed its whole job with
    ``RecursionError``."""
    path = ros2_mcap(
        tmp_path / "loop.mcap", ("/loop", "pkg/msg/Foo", definition, bytes(12)), GOOD_STRING
    )
    with Bag.open(path) as bag:
        problems = {c.topic: c.problem for c in bag.connections}
        good = list(decoded(bag, ["/ok"]))
    assert "a type holding itself" in (problems["/loop"] or "")
    assert cycle in (problems["/loop"] or "")
    assert problems["/ok"] is None
    assert [message for _, _, message in good] == [{"data": "hi"}]


@pytest.fixture
def service_recursion_limit() -> Iterator[None]:
    """The storage service's recursion limit, where this test process has py_ecc's."""
    previous = sys.getrecursionlimit()
    sys.setrecursionlimit(1000)
    yield
    sys.setrecursionlimit(previous)


@pytest.mark.usefixtures("service_recursion_limit")
def test_types_nested_past_the_bound_disable_only_their_topic(tmp_path: Path) -> None:
    """600 types chained, 65 kB of definition, raised ``RecursionError`` in rosbags and
    failed the whole bag; as deep as the bound, they decode under the service's limit."""
    path = ros2_mcap(
        tmp_path / "deep.mcap",
        ("/deep", "pkg/msg/T0", chained_types(600), bytes(8)),
        ("/bound", "pkg/msg/T0", chained_types(MAX_TYPE_DEPTH), b"\x00\x01\x00\x00*\x00\x00\x00"),
        GOOD_STRING,
    )
    with Bag.open(path) as bag:
        problems = {c.topic: c.problem for c in bag.connections}
        [(_, _, message)] = decoded(bag, ["/bound"])
    assert problems["/deep"] == (
        f"the bag's definition nests types more than {MAX_TYPE_DEPTH} deep "
        f"(from pkg/msg/T0 through pkg/msg/T{MAX_TYPE_DEPTH})"
    )
    assert (problems["/bound"], problems["/ok"]) == (None, None)
    for _ in range(MAX_TYPE_DEPTH - 1):
        message = message["next"]
    assert message == {"x": 42}


def test_definitions_past_the_bags_text_bound_disable_only_their_topics(tmp_path: Path) -> None:
    """Nothing bounded a definition's text, which rosbags parses at about a megabyte a
    second on the ingest thread: each distinct definition is charged to the bag's
    ``MAX_DEFINITION_BYTES`` before it is parsed, and the one past them is not parsed."""
    comment = "# " + "x" * 1000 + "\n"
    large = "int32 x\n" + comment * (MAX_DEFINITION_BYTES // len(comment) // 2 + 1)
    message = b"\x00\x01\x00\x00*\x00\x00\x00"
    path = ros2_mcap(
        tmp_path / "large.mcap",
        ("/first", "pkg/msg/First", large, message),
        ("/second", "pkg/msg/Second", large, message),
        GOOD_STRING,
    )
    with Bag.open(path) as bag:
        problems = {c.topic: c.problem for c in bag.connections}
        first = [message for _, _, message in decoded(bag, ["/first", "/ok"])]
    left = MAX_DEFINITION_BYTES - len(large)
    assert problems["/second"] == (
        f"the bag's definition holds {len(large)} bytes of text, more than the {left} left "
        f"of the {MAX_DEFINITION_BYTES} a bag's definitions may hold (rosbags parses about a "
        "megabyte a second)"
    )
    assert (problems["/first"], problems["/ok"]) == (None, None)
    assert first == [{"x": 42}, {"data": "hi"}]


def test_a_service_definition_bare_or_headed_gives_one_event_type() -> None:
    """Bare, as rosbag2 wrote it in Iron and Jazzy, or headed ``SRV:``, as rosbag2 writes it
    since (ros2/rosbag2#2365); ``ServiceEventInfo`` as rosbags defines it."""
    event = "example_interfaces/srv/AddTwoInts_Event"
    bare = "int64 a\nint64 b\n---\nint64 sum\n"
    headed = f"{'=' * 80}\nSRV: example_interfaces/srv/AddTwoInts\n{bare}"
    types = service_event_types(event, bare)
    assert types is not None
    assert service_event_types(event, headed) == types
    store = get_typestore(Stores.EMPTY)
    store.register(types)
    info = get_typestore(Stores.ROS2_JAZZY).fielddefs["service_msgs/msg/ServiceEventInfo"]
    assert store.fielddefs["service_msgs/msg/ServiceEventInfo"] == info
    request = store.fielddefs["example_interfaces/srv/AddTwoInts_Request"]
    response = store.fielddefs["example_interfaces/srv/AddTwoInts_Response"]
    assert [name for name, _ in request[1]] == ["a", "b"]
    assert [name for name, _ in response[1]] == ["sum"]
    assert [name for name, _ in store.fielddefs[event][1]] == ["info", "request", "response"]


@pytest.mark.parametrize(
    ("msgtype", "definition"),
    [
        ("example_interfaces/msg/AddTwoInts", "int64 a\n---\nint64 sum\n"),
        (
            "example_interfaces/srv/AddTwoInts_Event",
            "service_msgs/ServiceEventInfo info\n"
            "example_interfaces/srv/AddTwoInts_Request[<=1] request\n",
        ),
    ],
    ids=["not-an-event", "the-events-own"],
)
def test_only_an_event_given_its_services_definition_is_rebuilt(
    msgtype: str, definition: str
) -> None:
    assert service_event_types(msgtype, definition) is None


def test_message_type_without_definition(tmp_path: Path) -> None:
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg("int32 value", "my_msgs/msg/Counter"))
    counter = store.types["my_msgs/msg/Counter"]
    with Rosbag2Writer(tmp_path / "custom", version=8) as writer:
        connection = writer.add_connection(
            "/counter", "my_msgs/msg/Counter", msgdef="", rihs01="RIHS01_" + "0" * 64
        )
        writer.write(connection, 5, store.serialize_cdr(counter(value=3), "my_msgs/msg/Counter"))
    with Bag.open(tmp_path / "custom") as bag:
        (listed,) = bag.connections
        assert listed.definition_format == "none"
        assert listed.definition_source is None
        assert "no definition of my_msgs/msg/Counter" in (listed.problem or "")
        with pytest.raises(MissingDefinition) as caught:
            list(decoded(bag))
    assert (caught.value.topic, caught.value.msgtype) == ("/counter", "my_msgs/msg/Counter")


def test_fixed_arrays_rosbags_unrolls_are_bounded_per_bag(tmp_path: Path) -> None:
    """rosbags generates a line of Python per element of a fixed-size array of strings or
    messages when it builds a type's (de)serializers, which opening a bag does: 17 bytes of
    definition, ``string[100000] names``, took 129 s and 3.9 GiB. A bag's definitions hold
    at most ``MAX_UNROLLED`` such elements together, each distinct definition counted once;
    the definition past them disables its topics alone (bound, they fail as undefined)."""
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("geometry_msgs/Point[4] corners", "wide_msgs/msg/Corners"))
    store.register(get_types_from_msg("string[600] names", "wide_msgs/msg/Names"))
    store.register(get_types_from_msg("string[600] more", "wide_msgs/msg/More"))
    corners = store.types["wide_msgs/msg/Corners"]
    point = store.types["geometry_msgs/msg/Point"]
    path = tmp_path / "wide.bag"
    with Rosbag1Writer(path) as writer:
        listed = {
            topic: writer.add_connection(topic, f"wide_msgs/msg/{name}", typestore=store)
            for topic, name in [
                ("/corners", "Corners"),
                ("/names", "Names"),
                ("/names_again", "Names"),
                ("/more", "More"),
            ]
        }
        message = corners(corners=[point(x=float(n), y=0.0, z=0.0) for n in range(4)])
        raw = store.serialize_ros1(message, "wide_msgs/msg/Corners")
        writer.write(listed["/corners"], START_NS, raw)
    with Bag.open(path) as bag:
        problems = {connection.topic: connection.problem for connection in bag.connections}
        messages = list(decoded(bag))
    left = MAX_UNROLLED - 4 - 600
    assert problems == {
        "/corners": None,
        "/names": None,
        "/names_again": None,
        "/more": (
            "the bag's definition holds 600 elements of fixed-size arrays of strings or "
            f"messages, more than the {left} left of the {MAX_UNROLLED} a bag's definitions "
            "may hold (rosbags generates code for each)"
        ),
    }
    assert [(topic, message["corners"][3]["x"]) for topic, _, message in messages] == [
        ("/corners", 3.0)
    ]


def test_a_bag_of_more_topics_than_a_bag_may_hold_is_refused_at_open(tmp_path: Path) -> None:
    """Empty connections cost the ingest thread a typestore entry and a draft each, and the
    job a line each of a report saved at every step (21 MB for 40,000 IMU topics)."""
    store = get_typestore(Stores.ROS1_NOETIC)
    path = tmp_path / "many.bag"
    with Rosbag1Writer(path) as writer:
        for index in range(MAX_TOPICS + 1):
            writer.add_connection(f"/t{index}", "std_msgs/msg/String", typestore=store)
    with pytest.raises(BagUnreadable) as refused:
        Bag.open(path)
    assert str(refused.value) == (
        f"many.bag: holds {MAX_TOPICS + 1} topics, more than the {MAX_TOPICS} a bag may"
    )


@pytest.mark.parametrize(
    ("topic", "msgtype"),
    [("/t", "pkg/msg/" + "A" * (MAX_NAME - 7)), ("/" + "t" * MAX_NAME, "std_msgs/msg/String")],
    ids=["type", "topic"],
)
def test_a_bag_with_a_name_past_the_bound_is_refused_at_open(
    tmp_path: Path, topic: str, msgtype: str
) -> None:
    """A type name of a megabyte made a job's report of a megabyte, written again at each
    step of the job, and a bag may hold 4,096 of them."""
    path = ros2_mcap(tmp_path / "long.mcap", (topic, msgtype, "int32 x\n", bytes(8)), GOOD_STRING)
    with pytest.raises(BagUnreadable) as refused:
        Bag.open(path)
    assert str(refused.value) == (
        f"long.mcap: holds a topic or type name of {MAX_NAME + 1} characters, more than the "
        f"{MAX_NAME} a bag's names may have"
    )


NO_BYTES = "an array of a message that serialises to no bytes"
CDR_EMPTY = b"\x00\x01\x00\x00"
"""A CDR message's encapsulation header (little endian) and nothing after it."""


def nested(store: Any, package: str, leaf: str, levels: int = 6, length: int = 40) -> str:
    """Register ``levels`` message types each holding a fixed-size array of ``length`` of the
    next, down to one defined by ``leaf``: 40**6 (4 billion) leaves for 240 lines of
    rosbags' code. The outermost type's name."""
    store.register(get_types_from_msg(leaf, f"{package}/msg/Level{levels}"))
    for level in reversed(range(levels)):
        inner = f"{package}/Level{level + 1}[{length}] next"
        store.register(get_types_from_msg(inner, f"{package}/msg/Level{level}"))
    return f"{package}/msg/Level0"


def no_bytes(field: str, generation: str = " in ROS 1") -> str:
    return (
        f"the bag's definition holds {field}, {NO_BYTES}{generation}: a message of a few "
        "bytes could decode to billions of them"
    )


def as_written(store: Any, msgtype: str, ros_version: int) -> str:
    """``msgtype``'s definition as a bag would carry it, with its arrays of length 0, which
    rosbags' writer writes as sequences (``[]``) where a definition's own text keeps them."""
    text = store.generate_msgdef(msgtype, ros_version=ros_version)[0]
    return text.replace("[] none", "[0] none").replace("[] padding", "[0] padding")


def test_arrays_of_messages_of_no_bytes_are_refused_at_open_in_ros1(tmp_path: Path) -> None:
    """In ROS 1 a message without fields serialises to no bytes, so ``std_msgs/Empty[]`` in a
    message of 8 bytes whose length said 0xFFFFFFFF had rosbags create 4.3 billion objects
    (1,000,000 took 1.35 s), and nested fixed-size arrays of them multiply from a message of
    none. Such a definition disables its topics at open, before any message is decoded; a
    sequence of real messages and an array of length 0 stay, and the bag's others decode."""
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("int32 seq\nstd_msgs/Empty[] items", "hollow_msgs/msg/Items"))
    cube = nested(store, "cube_msgs", "std_msgs/Empty nothing")
    points = "hollow_msgs/msg/Points"
    store.register(
        get_types_from_msg("geometry_msgs/Point[] points\nstd_msgs/Empty[0] none", points)
    )
    point = store.types["geometry_msgs/msg/Point"]
    message = store.types[points](points=[point(x=1.0, y=2.0, z=3.0)], none=[])
    md5 = store.generate_msgdef(points)[1]
    path = tmp_path / "hollow.bag"
    with Rosbag1Writer(path) as writer:
        for topic, msgtype, raw in [
            ("/items", "hollow_msgs/msg/Items", struct.pack("<iI", 7, 0xFFFFFFFF)),
            ("/cube", cube, b""),
        ]:
            writer.write(writer.add_connection(topic, msgtype, typestore=store), START_NS, raw)
        listed = writer.add_connection(
            "/points", points, msgdef=as_written(store, points, 1), md5sum=md5
        )
        writer.write(listed, START_NS, store.serialize_ros1(message, points))
    with Bag.open(path) as bag:
        problems = {connection.topic: connection.problem for connection in bag.connections}
        assert problems == {
            "/items": no_bytes("hollow_msgs/msg/Items.items"),
            "/cube": no_bytes("cube_msgs/msg/Level0.next"),
            "/points": None,
        }
        points = [message for _, _, message in decoded(bag, topics=["/points"])]
        with pytest.raises(MissingDefinition) as caught:
            list(decoded(bag, topics=["/items"]))
    assert points == [{"points": [{"x": 1.0, "y": 2.0, "z": 3.0}], "none": []}]
    assert caught.value.reason == problems["/items"]


def test_cdr_refuses_only_the_arrays_of_no_bytes_it_cannot_bound(tmp_path: Path) -> None:
    """CDR gives a message without fields a byte (ROS 2's IDL), and rosbags checks a
    sequence's length against the bytes left, so ``std_msgs/Empty[]`` of 0xFFFFFFFF and
    nested arrays of ``std_msgs/Empty`` in a message too short for them are undecodable at
    once, and stay. A message whose fields are all arrays of length 0 takes no bytes in CDR
    too: nested fixed-size arrays of it are refused."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg("int32 seq\nstd_msgs/Empty[] items", "hollow_msgs/msg/Items"))
    crates = nested(store, "crate_msgs", "std_msgs/Empty nothing")
    cube = nested(store, "cube_msgs", "uint8[0] padding")
    items = CDR_EMPTY + struct.pack("<iI", 7, 0xFFFFFFFF)
    topics = [("/items", "hollow_msgs/msg/Items", items), ("/crates", crates, CDR_EMPTY)]
    with Rosbag2Writer(tmp_path / "hollow", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, msgtype, raw in topics:
            writer.write(writer.add_connection(topic, msgtype, typestore=store), START_NS, raw)
        definition = as_written(store, cube, 2)
        listed = writer.add_connection(
            "/cube", cube, msgdef=definition, rihs01="RIHS01_" + "0" * 64
        )
        writer.write(listed, START_NS, CDR_EMPTY)
    with Bag.open(tmp_path / "hollow") as bag:
        problems = {connection.topic: connection.problem for connection in bag.connections}
        assert problems == {
            "/items": None,
            "/crates": None,
            "/cube": no_bytes("cube_msgs/msg/Level0.next", ""),
        }
        for topic, _, _ in topics:
            with pytest.raises(MessageUndecodable, match=r"Invalid sequence length|unpack"):
                list(decoded(bag, topics=[topic]))


def test_no_real_recording_or_bundled_type_holds_an_array_of_no_bytes() -> None:
    """The refusal above takes nothing real: no connection of the recordings under
    shared/data, no type of rosbags' bundled typestores, in either generation's rules."""
    refused = []
    for entry in MANIFEST:
        with Bag.open(DATA / entry["path"]) as bag:
            refused += [c.topic for c in bag.connections if NO_BYTES in (c.problem or "")]
    assert refused == []
    for name in Stores:
        types = get_typestore(name).fielddefs
        for msgtype in types:
            for ros1 in (True, False):
                assert hollow_array(types, msgtype, ros1=ros1) is None, (name, msgtype, ros1)


def test_empty_bag_has_connections_and_no_messages() -> None:
    with Bag.open(DATA / "rosbag2/rosbag2_empty_bag") as bag:
        assert {c.topic for c in bag.connections} == {"/rosout", "/parameter_events"}
        assert bag.message_count == 0
        assert list(decoded(bag)) == []


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.99])
def test_truncated_ros1_bag_names_the_file(tmp_path: Path, fraction: float) -> None:
    original = generated(tmp_path, "ros1", 200).read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(original[: int(len(original) * fraction)])
    with pytest.raises(BagCorrupt) as caught:
        Bag.open(cut)
    assert caught.value.path == cut
    assert str(caught.value).startswith("cut.bag")
    assert str(tmp_path) not in str(caught.value)


def test_corrupt_ros1_chunk_names_its_offset(tmp_path: Path) -> None:
    path = generated(tmp_path, "ros1", 2000)
    with Bag.open(path) as bag:
        chunk_positions = sorted(bag._sources[0][0].chunks)
    assert len(chunk_positions) > 2
    target = chunk_positions[1]
    damaged = bytearray(path.read_bytes())
    damaged[target + 200 : target + 264] = b"\xff" * 64
    path.write_bytes(bytes(damaged))
    with Bag.open(path) as bag, pytest.raises(BagCorrupt) as caught:
        list(decoded(bag))
    assert caught.value.offset == target
    assert f"at byte {target}" in str(caught.value)


@pytest.mark.parametrize("fraction", [0.5, 0.999])
def test_truncated_mcap_names_file_and_offset(tmp_path: Path, fraction: float) -> None:
    source = DATA / "mcap/robot_localization_test2_mcap/robot_localization_test2_mcap.mcap"
    data = source.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(BagCorrupt) as caught:
        Bag.open(cut)
    assert caught.value.path == cut
    assert caught.value.offset is not None
    assert 0 < caught.value.offset <= len(data)


@pytest.mark.parametrize("length", [8, 9, 40])
def test_an_mcap_cut_after_its_magic_is_corrupt_unchecked_too(tmp_path: Path, length: int) -> None:
    """Opened unchecked (staging processes check alongside), rosbags' reader raised TypeError
    on the missing first record, and the ingest job failed as ingest_failed."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((DATA / "mcap/rosbag2_cpp_only_topics.mcap").read_bytes()[:length])
    for check in (False, True):
        with pytest.raises(BagCorrupt) as caught:
            Bag.open(cut, check=check)
        assert caught.value.path == cut


def test_corrupt_compressed_mcap_chunk_is_an_error_not_a_lost_message(tmp_path: Path) -> None:
    """rosbags alone drops the damaged chunk's messages without a word."""
    source = DATA / "mcap/cartographer_b0_short_mcap_zstd"
    copy = tmp_path / "copy"
    shutil.copytree(source, copy)
    storage = copy / "cartographer_b0_short_mcap_zstd.mcap"
    damaged = bytearray(storage.read_bytes())
    middle = len(damaged) // 2
    damaged[middle : middle + 64] = b"\xff" * 64
    storage.write_bytes(bytes(damaged))
    with Bag.open(copy) as bag, pytest.raises(BagCorrupt) as caught:
        list(bag.raw_messages())
    assert caught.value.path == storage
    assert "index counts" in str(caught.value)


def test_corrupt_mcap_chunk_names_its_offset(tmp_path: Path) -> None:
    source = DATA / "mcap/rosbag2_wbag_mcap"
    copy = tmp_path / "copy"
    shutil.copytree(source, copy)
    storage = copy / "wbag_2.mcap"
    damaged = bytearray(storage.read_bytes())
    damaged[4000:4016] = bytes(16)
    storage.write_bytes(bytes(damaged))
    with pytest.raises(BagCorrupt) as caught:
        Bag.open(copy)
    assert caught.value.path == storage
    assert caught.value.offset == 45
    assert "damaged MCAP record" in str(caught.value)


def test_corrupt_sqlite_storage(tmp_path: Path) -> None:
    path = generated(tmp_path, "sqlite3", 500)
    storage = next(path.glob("*.db3"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    with pytest.raises(BagCorrupt) as caught:
        Bag.open(path)
    assert "malformed" in str(caught.value)


def test_not_a_bag(tmp_path: Path) -> None:
    text = tmp_path / "notes.bag"
    text.write_text("not a bag at all\n")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    bare_directory = tmp_path / "dir"
    bare_directory.mkdir()
    with pytest.raises(BagUnreadable, match="not a ROS 1 bag"):
        Bag.open(text)
    with pytest.raises(BagCorrupt, match="empty") as caught:
        Bag.open(empty)
    assert caught.value.offset == 0
    with pytest.raises(BagUnreadable, match=r"metadata\.yaml"):
        Bag.open(bare_directory)


def test_bare_file_with_the_wrong_suffix(tmp_path: Path) -> None:
    source = DATA / "mcap/rosbag2_cpp_only_topics.mcap"
    renamed = tmp_path / "recording.bin"
    renamed.write_bytes(source.read_bytes())
    with pytest.raises(BagUnreadable, match=r"\*\.mcap"):
        Bag.open(renamed)


def test_an_mcap_chunk_declaring_more_than_a_chunk_may_hold_is_refused_unread(
    tmp_path: Path,
) -> None:
    """32 KiB of zstd declaring 1 GiB of zeros: the mcap library decompressed it whole (2.1
    GiB in the service). Refused on its declaration, before a byte is decompressed, both by
    the check and by rosbags' reader (which staging processes open unchecked)."""
    bomb = tmp_path / "bomb.mcap"
    offset = write_mcap_bomb(bomb)
    assert bomb.stat().st_size < 64 * 1024
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for check in (True, False):
        with pytest.raises(BagUnreadable) as refused:
            Bag.open(bomb, check=check)
        assert refused.value.offset == offset
        assert refused.value.reason == (
            f"chunk declares {1 << 30} bytes decompressed, more than the {MAX_CHUNK_BYTES} "
            "a chunk may hold"
        )
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 64 * 1024  # KiB


def test_a_chunk_past_its_declared_size_is_cut_off_there() -> None:
    from backports import zstd

    with pytest.raises(ChunkTooLarge, match="more than 1024 bytes"):
        inflate_declared("zstd", zstd.compress(bytes(1 << 20)), 1024)
    assert inflate_declared("zstd", zstd.compress(b"x" * 1024), 1024) == b"x" * 1024
    with pytest.raises(ValueError, match="not one whole frame"):
        inflate_declared("zstd", zstd.compress(b"x") + zstd.compress(bytes(1 << 20)), 1024)


def test_a_ros1_chunk_past_the_limit_is_refused_naming_it(tmp_path: Path) -> None:
    """rosbags decompresses a ROS 1 chunk whole (bz2, lz4) and keeps no size to check it by."""
    bag = write_ros1_big_chunk(tmp_path / "big.bag", MAX_CHUNK_BYTES)
    with Bag.open(bag) as opened, pytest.raises(BagUnreadable) as refused:
        list(decoded(opened))
    assert refused.value.offset == 13 + 4096  # after the magic and the bag header record
    assert refused.value.reason == f"chunk decompresses to more than {MAX_CHUNK_BYTES} bytes (lz4)"
