"""Draft templates from message definitions, converters checked against rosbags' own
deserialisation and the template validator, bindings."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from robocloud.templates import MAX_DESCRIPTION, MAX_FIELDS, Template, parse_template, validate_data
from robocloud.unixfs import import_bytes
from services.storage.bags import Bag
from services.storage.matcher import (
    BindingInvalid,
    BindingRefused,
    Bindings,
    ConversionError,
    Converter,
    DraftError,
    compile_converter,
    draft_name,
    draft_template,
)
from tests.bagfactory import BagKind, fanout_store, write_bag
from tests.blobs import MemoryBlobs

DATA = Path(__file__).resolve().parents[5] / "shared" / "data"
HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
NOETIC = get_typestore(Stores.ROS1_NOETIC)
VECTOR = {"container": {"x": "float", "y": "float", "z": "float"}}
STAMP = {"container": {"sec": "int", "nanosec": "int"}}


def test_draft_names() -> None:
    assert draft_name("sensor_msgs/msg/NavSatFix") == "nav_sat_fix"
    assert draft_name("sensor_msgs/msg/Imu") == "imu"
    assert draft_name("sensor_msgs/msg/MultiEchoLaserScan") == "multi_echo_laser_scan"
    assert draft_name("my_pkg/msg/GPSFix") == "gps_fix"


@pytest.mark.parametrize("store", [HUMBLE, NOETIC], ids=["ros2", "ros1"])
def test_imu_draft(store: Any) -> None:
    draft = draft_template(store, "sensor_msgs/msg/Imu")
    assert draft["name"] == "imu"
    assert draft["version"] == 1
    assert draft["fields"] == {
        "frame_id": "string",
        "orientation": {"container": {"x": "float", "y": "float", "z": "float", "w": "float"}},
        "orientation_covariance": {"array": "float"},
        "angular_velocity": VECTOR,
        "angular_velocity_covariance": {"array": "float"},
        "linear_acceleration": VECTOR,
        "linear_acceleration_covariance": {"array": "float"},
    }
    assert parse_template(draft).id == "imu@1"


def test_navsatfix_and_image_drafts() -> None:
    fix = draft_template(HUMBLE, "sensor_msgs/msg/NavSatFix")["fields"]
    assert fix["status"] == {"container": {"status": "int", "service": "int"}}
    assert fix["latitude"] == "float"
    assert fix["position_covariance_type"] == "int"
    image = draft_template(HUMBLE, "sensor_msgs/msg/Image")["fields"]
    assert image == {
        "frame_id": "string",
        "height": "int",
        "width": "int",
        "encoding": "string",
        "is_bigendian": "int",
        "step": "int",
        "data": "image",
    }
    compressed = draft_template(HUMBLE, "sensor_msgs/msg/CompressedImage")["fields"]
    assert compressed == {"frame_id": "string", "format": "string", "data": "image"}
    cloud = draft_template(HUMBLE, "sensor_msgs/msg/PointCloud2")["fields"]
    assert cloud["data"] == "file"
    assert cloud["fields"] == {
        "array": {
            "container": {"name": "string", "offset": "int", "datatype": "int", "count": "int"}
        }
    }


def test_nested_headers_times_and_durations() -> None:
    tf = draft_template(HUMBLE, "tf2_msgs/msg/TFMessage")["fields"]
    transform = tf["transforms"]["array"]["container"]
    assert transform["header"] == {"container": {"stamp": STAMP, "frame_id": "string"}}
    assert transform["child_frame_id"] == "string"
    store = get_typestore(Stores.EMPTY)
    store.register(HUMBLE.fielddefs)
    store.register(
        get_types_from_msg(
            "builtin_interfaces/Duration timeout\nbuiltin_interfaces/Time deadline\n"
            "uint8[16] uuid\nbool[] flags",
            "my_msgs/msg/Task",
        )
    )
    fields = draft_template(store, "my_msgs/msg/Task")["fields"]
    assert fields == {
        "timeout": "int",
        "deadline": STAMP,
        "uuid": {"array": "int"},
        "flags": {"array": "bool"},
    }


def test_a_draft_from_a_ros1_recording_binds_the_ros2_recordings_of_its_type() -> None:
    """evo's tf example is in shared/data as a ROS 1 bag and as a ROS 2 bag. Its ROS 1
    draft kept ``transforms[].header.seq``, which ROS 2's header has not, so the template
    bound to ``tf2_msgs/msg/TFMessage`` failed every ROS 2 job of that type."""
    drafts: dict[str, dict[str, dict[str, Any]]] = {"ros1": {}, "ros2": {}}
    stores: dict[str, dict[str, Any]] = {"ros1": {}, "ros2": {}}
    for path in [*DATA.glob("rosbag1/*.bag"), *DATA.glob("rosbag2/*"), *DATA.glob("mcap/*")]:
        generation = "ros1" if path.suffix == ".bag" else "ros2"
        with Bag.open(path) as bag:
            for connection in bag.connections:
                if connection.typestore is not None:
                    store = connection.typestore
                    drafts[generation][connection.msgtype] = draft_template(
                        store, connection.msgtype
                    )
                    stores[generation][connection.msgtype] = store
    both = sorted(set(drafts["ros1"]) & set(drafts["ros2"]))
    assert {"tf2_msgs/msg/TFMessage", "nav_msgs/msg/Odometry", "sensor_msgs/msg/Imu"} <= set(both)
    for msgtype in both:
        assert drafts["ros1"][msgtype] == drafts["ros2"][msgtype], msgtype
        for drafted_from, bound_to in (("ros1", "ros2"), ("ros2", "ros1")):
            template = parse_template(drafts[drafted_from][msgtype])
            compile_converter(template, stores[bound_to][msgtype], msgtype)


def flat_store(fields: int) -> Any:
    store = get_typestore(Stores.EMPTY)
    text = "\n".join(f"float64 x{n}" for n in range(fields))
    store.register(get_types_from_msg(text, "fan_msgs/msg/Flat"))
    return store


def test_a_draft_walks_no_more_fields_than_a_template_holds() -> None:
    """Eight definitions of five fields each drafted 5**8 = 390,625 leaves (1.5 s, 100 MiB),
    sixteen fields each 16**8, which never finished: each nested type is written once in a
    definition however often it is used, so a few lines of a bag's schema (which anyone can
    upload) held the ingest thread and took the service's memory. No template can hold
    more than ``MAX_FIELDS`` fields, so the draft stops as soon as it walked more."""
    with pytest.raises(DraftError) as fanned:
        draft_template(fanout_store(5, 7), "fan_msgs/msg/Level0")
    assert fanned.value.reason == f"holds more than {MAX_FIELDS} fields"
    assert fanned.value.path == "f0.f0.f0.f1.f1.f2.f3.x0"  # the 1,025th field, depth first
    with pytest.raises(DraftError) as flat:
        draft_template(flat_store(MAX_FIELDS + 1), "fan_msgs/msg/Flat")
    assert flat.value.path == f"x{MAX_FIELDS}"
    widest = draft_template(flat_store(MAX_FIELDS), "fan_msgs/msg/Flat")
    assert len(parse_template(widest).fields) == MAX_FIELDS
    nested = draft_template(fanout_store(4, 3), "fan_msgs/msg/Level0")  # 4+16+64+256 fields
    assert parse_template(nested).field_at("f3.f3.f3.x3") is not None


def test_a_type_of_a_long_name_drafts_a_valid_template() -> None:
    """The description named the type whole: a bag's type of 5,000 characters drafted a
    description past ``MAX_DESCRIPTION``, which no ``templates create`` accepted."""
    store = get_typestore(Stores.ROS1_NOETIC)
    msgtype = "long_msgs/msg/" + "L" * 5000
    store.register(get_types_from_msg("float64 x", msgtype))
    template = parse_template(draft_template(store, msgtype))
    assert template.name == "l" * 63
    assert template.description.startswith("Drafted from long_msgs/msg/LLL")
    assert template.description.endswith("LLL....")
    assert len(template.description) <= MAX_DESCRIPTION


def test_every_type_in_the_real_recordings_drafts_a_valid_template() -> None:
    drafted = set()
    for path in [*DATA.glob("rosbag1/*.bag"), *DATA.glob("rosbag2/*"), *DATA.glob("mcap/*")]:
        with Bag.open(path) as bag:
            for connection in bag.connections:
                if connection.typestore is None or connection.msgtype in drafted:
                    continue
                template = parse_template(draft_template(connection.typestore, connection.msgtype))
                assert template.fields, connection.msgtype
                drafted.add(connection.msgtype)
    assert {"sensor_msgs/msg/MultiEchoLaserScan", "nav_msgs/msg/Odometry"} <= drafted
    assert {"test_msgs/msg/Arrays", "rcl_interfaces/msg/ParameterEvent"} <= drafted
    assert {"example_interfaces/srv/AddTwoInts_Event", "test_msgs/srv/BasicTypes_Event"} <= drafted
    assert len(drafted) >= 12


def _stamp_ns(message: Any) -> int:
    return int(message.header.stamp.sec) * 1_000_000_000 + int(message.header.stamp.nanosec)


def deserialized(bag: Bag) -> Iterator[tuple[str, int, Any]]:
    """Every message of ``bag`` as rosbags deserializes it, with its topic and time."""
    for connection, t_ns, raw in bag.raw_messages():
        yield connection.topic, t_ns, bag.deserialize(connection, t_ns, raw)


def draft_converters(bag: Bag) -> dict[str, tuple[Template, Converter]]:
    """Each topic's draft template, approved as it is, and its converter."""
    converters = {}
    for connection in bag.connections:
        assert connection.typestore is not None
        template = parse_template(draft_template(connection.typestore, connection.msgtype))
        converters[connection.topic] = (
            template,
            compile_converter(template, connection.typestore, connection.msgtype),
        )
    return converters


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_records_from_generated_bags_match_rosbags(tmp_path: Path, kind: BagKind) -> None:
    path = write_bag(tmp_path / ("g.bag" if kind == "ros1" else "g"), kind, 30)
    blobs = MemoryBlobs()
    produced = []
    with Bag.open(path) as bag:
        converters = draft_converters(bag)
        for topic, t_ns, message in deserialized(bag):
            template, converter = converters[topic]
            data = converter.data(message, blobs)
            validate_data(template, data)
            produced.append((topic, converter.record_time(message, t_ns), data))
    with AnyReader([path]) as reader:
        originals = [
            (c.topic, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()
        ]
    assert len(produced) == len(originals) == 30
    for (topic, t, data), (expected_topic, message) in zip(produced, originals, strict=True):
        assert topic == expected_topic
        assert t == _stamp_ns(message)
        assert data["frame_id"] == message.header.frame_id
        if topic == "/imu":
            assert data["orientation"]["z"] == message.orientation.z
            assert data["linear_acceleration"] == {
                "x": message.linear_acceleration.x,
                "y": message.linear_acceleration.y,
                "z": message.linear_acceleration.z,
            }
            assert (
                data["angular_velocity_covariance"] == message.angular_velocity_covariance.tolist()
            )
        elif topic == "/gps":
            assert (data["latitude"], data["longitude"]) == (message.latitude, message.longitude)
            assert data["status"] == {"status": message.status.status, "service": 1}
            assert data["position_covariance"] == message.position_covariance.tolist()
        else:
            assert blobs.files[data["data"]] == message.data.tobytes()
            assert data["data"] == str(import_bytes(message.data.tobytes())[1])
            assert (data["width"], data["height"], data["encoding"]) == (8, 6, "rgb8")


def imu_template(fields: dict[str, Any]) -> Any:
    return parse_template({"name": "imu", "version": 2, "fields": fields})


def test_edited_template_keeps_only_its_fields_and_widens_types() -> None:
    template = imu_template(
        {
            "angular_velocity": {"container": {"z": "float"}},
            "frame_id": "string",
        }
    )
    converter = compile_converter(template, HUMBLE, "sensor_msgs/msg/Imu")
    message = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=0, nanosec=0), frame_id="base"),
        angular_velocity=SimpleNamespace(x=1.0, y=2.0, z=3),
    )
    assert converter.data(message, MemoryBlobs()) == {
        "angular_velocity": {"z": 3.0},
        "frame_id": "base",
    }
    assert converter.record_time(message, 42) == 42


@pytest.mark.parametrize(
    ("fields", "path", "reason"),
    [
        ({"heading": "float"}, "heading", "no field of the message fills it"),
        ({"orientation": "float"}, "orientation", "container"),
        ({"orientation": {"container": {"q": "float"}}}, "orientation.q", "no field"),
        ({"orientation_covariance": "image"}, "orientation_covariance", "byte array"),
        ({"frame_id": "int"}, "frame_id", "string"),
        ({"angular_velocity": {"container": {"x": "string"}}}, "angular_velocity.x", "float"),
        ({"orientation_covariance": {"array": "bool"}}, "orientation_covariance[]", "float"),
    ],
)
def test_binding_a_template_that_does_not_fit(
    fields: dict[str, Any], path: str, reason: str
) -> None:
    with pytest.raises(BindingInvalid) as caught:
        compile_converter(imu_template(fields), HUMBLE, "sensor_msgs/msg/Imu")
    assert caught.value.path == path
    assert reason in caught.value.reason
    assert caught.value.template_id == "imu@2"


def test_values_json_cannot_hold_are_refused_with_their_path() -> None:
    template = imu_template({"orientation": {"container": {"w": "float"}}})
    converter = compile_converter(template, HUMBLE, "sensor_msgs/msg/Imu")
    with pytest.raises(ConversionError) as caught:
        converter.data(SimpleNamespace(orientation=SimpleNamespace(w=math.nan)), MemoryBlobs())
    assert caught.value.path == "orientation.w"
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg("uint64 big", "my_msgs/msg/Big"))
    template = parse_template({"name": "big", "version": 1, "fields": {"big": "int"}})
    converter = compile_converter(template, store, "my_msgs/msg/Big")
    assert converter.data(SimpleNamespace(big=2**53 - 1), MemoryBlobs()) == {"big": 2**53 - 1}
    with pytest.raises(ConversionError, match=r"2\*\*53") as too_big:
        converter.data(SimpleNamespace(big=2**64 - 1), MemoryBlobs())
    assert too_big.value.path == "big"


def test_real_recording_records_validate_or_are_refused_by_path() -> None:
    """rosbag2's test_msgs carry int64 extremes: refused by path, never sent on to fail JCS."""
    validated, refused = [], []
    with Bag.open(DATA / "rosbag2/rosbag2_cdr_test_sqlite3") as bag:
        converters = draft_converters(bag)
        for topic, _, message in deserialized(bag):
            template, converter = converters[topic]
            try:
                data = converter.data(message, MemoryBlobs())
            except ConversionError as exc:
                refused.append((topic, exc.path))
                continue
            validate_data(template, data)
            validated.append(topic)
    assert validated == ["/test_topic"] * 3
    assert refused == [("/array_topic", "int64_values_default[]")] * 4


def test_bindings_resolve_persist_and_refuse(tmp_path: Path) -> None:
    path = tmp_path / "bindings.json"
    bindings = Bindings(path)
    bindings.bind(template_id="imu@1", msgtype="sensor_msgs/msg/Imu")
    bindings.bind(template_id="imu_front@2", topic="imu")
    assert bindings.resolve("/imu", "sensor_msgs/msg/Imu") == "imu_front@2"
    assert bindings.resolve("/imu/data", "sensor_msgs/msg/Imu") == "imu@1"
    assert bindings.resolve("/gps", "sensor_msgs/msg/NavSatFix") is None
    reopened = Bindings(path)
    assert reopened.to_json() == {
        "topics": {"/imu": "imu_front@2"},
        "msgtypes": {"sensor_msgs/msg/Imu": "imu@1"},
    }
    assert reopened.unbind(topic="/imu") is True
    assert reopened.unbind(topic="/imu") is False
    assert Bindings(path).resolve("/imu", "sensor_msgs/msg/Imu") == "imu@1"
    before = path.read_bytes()
    refusals = [
        ({"template_id": "IMU@1", "topic": "/imu"}, "template"),
        ({"template_id": "imu@0", "topic": "/imu"}, "template"),
        ({"template_id": "imu@1", "topic": "/bad topic"}, "topic"),
        ({"template_id": "imu@1", "msgtype": "not a type"}, "msgtype"),
        ({"template_id": "imu@1"}, "topic"),
        ({"template_id": "imu@1", "topic": "/a", "msgtype": "a/msg/B"}, "topic"),
    ]
    for arguments, field in refusals:
        with pytest.raises(BindingRefused) as caught:
            reopened.bind(**arguments)
        assert caught.value.field == field
    assert path.read_bytes() == before
