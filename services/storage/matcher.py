"""From ROS message types to templates: draft templates, topic bindings, message -> record data.

A draft is generated from a message definition so that a designer edits and approves a
template instead of typing one: nested messages become containers, arrays ``{"array": ...}``,
the pixel bytes of ``sensor_msgs/Image`` and ``CompressedImage`` an ``image`` (a CID in cas),
other byte sequences a ``file``. Time needs care: a record's ``t`` is exact at any size, but
values in ``data`` stay I-JSON, whose integers stop being exact at 2**53 (about 104 days of
nanoseconds), so that any JSON reader gets them right:

- a message's top-level ``std_msgs/Header`` is not copied: its stamp becomes the record's
  ``t`` (the bag's receive time when the stamp is zero) and its ``frame_id`` the string field
  ``frame_id``; ROS 1's ``seq`` is dropped, from every other header too: a publisher's
  counter that ROS 2's header no longer has, so a draft that kept it (``tf2_msgs/TFMessage``'s
  ``transforms[].header.seq``) bound no ROS 2 recording of the same type;
- any other ``time`` stays exact as a container ``{sec, nanosec}``;
- a ``duration`` becomes ``int`` nanoseconds, refused beyond 2**53.

A converter is compiled once per (template, message type): it checks up front that every
template field has a source in the message of a convertible type (raising
:class:`BindingInvalid` naming the path), so per-message work is only reading values and the
few checks values need (finite floats, integer bounds).
"""

from __future__ import annotations

import json
import math
import re
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from rosbags.interfaces import Nodetype
from rosbags.typesys.store import Typestore

from robocloud.jcs import MAX_SAFE_INTEGER
from robocloud.templates import (
    MAX_DESCRIPTION,
    MAX_FIELDS,
    MAX_NESTING,
    ArrayOf,
    Container,
    FieldType,
    Scalar,
    Template,
    finite_floats,
    parse_template_id,
    record_topic,
    recordable_topic,
)
from services.common.durable import atomic_write

HEADER = "std_msgs/msg/Header"
TIME = "builtin_interfaces/msg/Time"
DURATION = "builtin_interfaces/msg/Duration"
IMAGE_TYPES = frozenset({"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"})
BYTE_TYPES = frozenset({"uint8", "byte", "char"})
INT_TYPES = frozenset(
    {"int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64", "byte", "char"}
)
FLOAT_TYPES = frozenset({"float32", "float64", "float128"})
STRING_TYPES = frozenset({"string", "wstring"})
FRAME_ID = "frame_id"
NS = 1_000_000_000
MAX_BINDINGS = 10_000


class DraftError(Exception):
    """A message type that no template can describe (nesting or fields beyond the template
    limits)."""

    def __init__(self, msgtype: str, path: str, reason: str) -> None:
        super().__init__(f"{msgtype}: {path}: {reason}")
        self.msgtype = msgtype
        self.path = path
        self.reason = reason


class BindingInvalid(Exception):
    """A template cannot be filled from a message type; ``path`` names the template field."""

    def __init__(self, template_id: str, msgtype: str, path: str, reason: str) -> None:
        super().__init__(f"{template_id} from {msgtype}: {path}: {reason}")
        self.template_id = template_id
        self.msgtype = msgtype
        self.path = path
        self.reason = reason


class ConversionError(Exception):
    """One message's value does not fit its template (NaN, an integer beyond 2**53, ...)."""

    def __init__(self, path: str, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = path
        self.reason = reason


class BlobSink(Protocol):
    """Where ``image`` and ``file`` bytes go; returns the CID string a record holds."""

    def put(self, data: bytes) -> str: ...


def draft_name(msgtype: str) -> str:
    """``sensor_msgs/msg/NavSatFix`` -> ``nav_sat_fix``: a template name from a type name."""
    base = msgtype.rsplit("/", 1)[-1]
    snake = re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", base).lower()
    return field_name(snake)


def field_name(ros_name: str) -> str:
    """A template field name for a ROS field name (lowercase, invalid characters to ``_``)."""
    name = re.sub(r"[^a-z0-9_]", "_", ros_name.lower())
    if not name or not name[0].isalpha():
        name = f"f_{name}"
    return name[:63]


def has_header(store: Typestore, msgtype: str) -> bool:
    fields = store.fielddefs[msgtype][1]
    return any(name == "header" and desc == (Nodetype.NAME, HEADER) for name, desc in fields)


class _FieldBudget:
    """The fields a draft may walk: a template holds at most ``MAX_FIELDS``, through every
    container. A definition names each nested type once however often it is used, so the
    fields a draft expands grow as the product of the fields per level: eight lines of 16
    fields (an MCAP of 8 KB) drafted 16**8 leaves, and the ingest thread never finished."""

    def __init__(self, msgtype: str) -> None:
        self.msgtype = msgtype
        self.walked = 0

    def take(self, path: str) -> None:
        """Count the field at ``path``; :class:`DraftError` past ``MAX_FIELDS``."""
        self.walked += 1
        if self.walked > MAX_FIELDS:
            raise DraftError(self.msgtype, path, f"holds more than {MAX_FIELDS} fields")


def draft_template(store: Typestore, msgtype: str, *, name: str | None = None) -> dict[str, Any]:
    """A draft template document (the wire format) for ``msgtype``, version 1.

    :class:`DraftError` when no template can describe it: nested deeper than
    ``MAX_NESTING``, or more than ``MAX_FIELDS`` fields walked (those of empty messages,
    which the draft drops, included), found before any more is walked."""
    fields: dict[str, Any] = {}
    budget = _FieldBudget(msgtype)
    for ros_name, desc in store.fielddefs[msgtype][1]:
        budget.take(ros_name)
        if ros_name == "header" and desc == (Nodetype.NAME, HEADER):
            fields[FRAME_ID if FRAME_ID not in fields else "header_frame_id"] = "string"
            continue
        kind = _draft_type(store, msgtype, desc, ros_name, depth=1, budget=budget)
        if kind is not None:
            fields[field_name(ros_name)] = kind
    if not fields:
        raise DraftError(msgtype, "", "the message has no fields to record")
    return {
        "name": name or draft_name(msgtype),
        "version": 1,
        "fields": fields,
        "description": f"Drafted from {_shown_type(msgtype)}.",
    }


def _shown_type(msgtype: str) -> str:
    """``msgtype`` as a draft's description names it: a bag's type names are unbounded, and a
    description of more than ``MAX_DESCRIPTION`` characters made a draft no template could be
    created from."""
    limit = MAX_DESCRIPTION - 64
    return msgtype if len(msgtype) <= limit else f"{msgtype[:limit]}..."


def _draft_type(
    store: Typestore,
    msgtype: str,
    desc: Any,
    path: str,
    depth: int,
    *,
    budget: _FieldBudget,
    owner: str = "",
) -> Any:
    nodetype, detail = desc
    if depth > MAX_NESTING:
        raise DraftError(msgtype, path, f"nests deeper than {MAX_NESTING} levels")
    if nodetype == Nodetype.BASE:
        return _base_type(detail[0])
    if nodetype == Nodetype.NAME:
        if detail == DURATION:
            return "int"
        inner: dict[str, Any] = {}
        for ros_name, inner_desc in store.fielddefs[detail][1]:
            budget.take(f"{path}.{ros_name}")
            if detail == HEADER and ros_name == "seq":
                continue
            kind = _draft_type(
                store,
                msgtype,
                inner_desc,
                f"{path}.{ros_name}",
                depth + 1,
                budget=budget,
                owner=detail,
            )
            if kind is not None:
                inner[field_name(ros_name)] = kind
        return {"container": inner} if inner else None
    (element_type, element_detail), _size = detail
    if element_type == Nodetype.BASE and element_detail[0] in BYTE_TYPES:
        if nodetype == Nodetype.SEQUENCE:
            image = (owner or msgtype) in IMAGE_TYPES and path.rsplit(".", 1)[-1] == "data"
            return "image" if image else "file"
        return {"array": "int"}
    item = _draft_type(
        store, msgtype, (element_type, element_detail), f"{path}[]", depth + 1, budget=budget
    )
    return {"array": item} if item is not None else None


def _base_type(base: str) -> str:
    if base == "bool":
        return "bool"
    if base in INT_TYPES:
        return "int"
    if base in FLOAT_TYPES:
        return "float"
    return "string"


Convert = Callable[[Any], Any]


@dataclass(frozen=True)
class Converter:
    """Record data and time from one message as rosbags deserializes it: attributes read
    straight into the template's shape, with no plain copy of the message in between."""

    template_id: str
    msgtype: str
    header: bool
    convert: Callable[[Any, BlobSink], dict[str, Any]]

    def record_time(self, message: Any, received_ns: int) -> int:
        """The header stamp in nanoseconds, or the receive time when there is none (or 0)."""
        if self.header:
            stamp = message.header.stamp
            t = int(stamp.sec) * NS + int(stamp.nanosec)
            if t > 0:
                return t
        return received_ns

    def data(self, message: Any, blobs: BlobSink) -> dict[str, Any]:
        return self.convert(message, blobs)


def compile_converter(template: Template, store: Typestore, msgtype: str) -> Converter:
    """A converter filling ``template`` from messages of ``msgtype``; :class:`BindingInvalid`
    when a template field has no source or an unconvertible one."""
    header = has_header(store, msgtype)
    compiler = _Compiler(template.id, store, msgtype)
    sources = dict(store.fielddefs[msgtype][1])
    readers: list[tuple[str, str, Callable[[Any, BlobSink], Any]]] = []
    for name, kind in template.fields.items():
        if header and name in (FRAME_ID, "header_frame_id") and _frame_source(sources, name):
            compiler.expect_scalar(kind, "string", name)
            readers.append((name, "header", _frame_reader))
            continue
        ros_name = _source_name(sources, name, skip_header=header)
        if ros_name is None:
            raise BindingInvalid(template.id, msgtype, name, "no field of the message fills it")
        readers.append((name, ros_name, compiler.field(kind, sources[ros_name], name)))

    def convert(message: Any, blobs: BlobSink) -> dict[str, Any]:
        return {name: read(getattr(message, key), blobs) for name, key, read in readers}

    return Converter(template.id, msgtype, header, convert)


def _frame_source(sources: Mapping[str, Any], name: str) -> bool:
    return name == FRAME_ID or FRAME_ID in sources


def _frame_reader(header: Any, blobs: BlobSink) -> Any:
    return header.frame_id


def _source_name(sources: Mapping[str, Any], name: str, *, skip_header: bool) -> str | None:
    for ros_name in sources:
        if skip_header and ros_name == "header":
            continue
        if field_name(ros_name) == name:
            return ros_name
    return None


class _Compiler:
    def __init__(self, template_id: str, store: Typestore, msgtype: str) -> None:
        self.template_id = template_id
        self.store = store
        self.msgtype = msgtype

    def fail(self, path: str, reason: str) -> BindingInvalid:
        return BindingInvalid(self.template_id, self.msgtype, path, reason)

    def expect_scalar(self, kind: FieldType, wanted: str, path: str) -> None:
        if not (isinstance(kind, Scalar) and kind.kind == wanted):
            raise self.fail(path, f"the message holds a {wanted} here")

    def field(self, kind: FieldType, desc: Any, path: str) -> Callable[[Any, BlobSink], Any]:
        nodetype, detail = desc
        if nodetype == Nodetype.BASE:
            return self.scalar(kind, _base_type(detail[0]), path)
        if nodetype == Nodetype.NAME:
            if detail == DURATION and isinstance(kind, Scalar) and kind.kind == "int":
                return _duration_reader(path)
            if detail == TIME and isinstance(kind, Scalar) and kind.kind == "int":
                return _time_reader(path)
            if not isinstance(kind, Container):
                raise self.fail(path, f"the message holds a {detail} here (a container)")
            return self.container(kind, detail, path)
        (element_type, element_detail), _size = detail
        element = (element_type, element_detail)
        is_bytes = element_type == Nodetype.BASE and element_detail[0] in BYTE_TYPES
        if isinstance(kind, Scalar) and kind.kind in ("image", "file"):
            if not is_bytes:
                raise self.fail(path, f"{kind.kind} needs a byte array (uint8[]) in the message")
            return _blob_reader
        if isinstance(kind, Scalar) and kind.kind in ("range<int>", "range<float>"):
            if element_type != Nodetype.BASE or _size != 2:
                raise self.fail(path, "a range needs a fixed array of two numbers")
            return _range_reader(kind.kind == "range<int>", path)
        if not isinstance(kind, ArrayOf):
            raise self.fail(path, "the message holds an array here")
        item = self.field(kind.item, element, f"{path}[]")
        if is_bytes and isinstance(kind.item, Scalar) and kind.item.kind == "int":
            return lambda value, blobs: _plain_list(value)
        if isinstance(kind.item, Scalar) and kind.item.kind == "float":
            return _floats_reader(item)
        return lambda values, blobs: [item(value, blobs) for value in values]

    def container(self, kind: Container, msgtype: str, path: str) -> Callable[[Any, BlobSink], Any]:
        sources = dict(self.store.fielddefs[msgtype][1])
        readers: list[tuple[str, str, Callable[[Any, BlobSink], Any]]] = []
        for name, inner in kind.fields.items():
            ros_name = _source_name(sources, name, skip_header=False)
            if ros_name is None:
                raise self.fail(f"{path}.{name}", f"{msgtype} has no field that fills it")
            readers.append((name, ros_name, self.field(inner, sources[ros_name], f"{path}.{name}")))

        def convert(value: Any, blobs: BlobSink) -> dict[str, Any]:
            return {name: read(getattr(value, key), blobs) for name, key, read in readers}

        return convert

    def scalar(self, kind: FieldType, source: str, path: str) -> Callable[[Any, BlobSink], Any]:
        if not isinstance(kind, Scalar):
            raise self.fail(path, f"the message holds a {source} here")
        wanted = kind.kind
        if wanted == source == "string":
            return _identity
        if wanted == "float" and source in ("float", "int"):
            return _float_reader(path)
        if wanted == "int" and source in ("int", "bool"):
            return _int_reader(path)
        if wanted == "bool" and source in ("bool", "int"):
            return lambda value, blobs: bool(value)
        raise self.fail(path, f"a {wanted} cannot be filled from a {source}")


def _identity(value: Any, blobs: BlobSink) -> Any:
    return value


def _blob_reader(value: Any, blobs: BlobSink) -> str:
    return blobs.put(bytes(value))


def _float_reader(path: str) -> Callable[[Any, BlobSink], float]:
    def read(value: Any, blobs: BlobSink) -> float:
        number = float(value)
        if not math.isfinite(number):
            raise ConversionError(path, f"{number} is not a finite number (JSON has no NaN)")
        return number

    return read


def _floats_reader(item: Callable[[Any, BlobSink], float]) -> Callable[[Any, BlobSink], Any]:
    """An array of floats (covariances, ranges; a numpy array as rosbags gives it) as a list,
    when every item is a finite float (their sum is finite), without a call per item; else
    item by item, which converts integers and names the first NaN."""

    def read(values: Any, blobs: BlobSink) -> list[Any]:
        plain = _plain_list(values)
        if finite_floats(plain):
            return plain
        return [item(value, blobs) for value in plain]

    return read


def _plain_list(values: Any) -> list[Any]:
    """A numpy array (rosbags' numeric arrays) or a sequence as a list of Python values."""
    if hasattr(values, "tolist"):
        result: list[Any] = values.tolist()
        return result
    return list(values)


def _int_reader(path: str) -> Callable[[Any, BlobSink], int]:
    def read(value: Any, blobs: BlobSink) -> int:
        number = int(value)
        if abs(number) > MAX_SAFE_INTEGER:
            raise ConversionError(path, f"{number} is beyond +-(2**53 - 1), JSON's exact integers")
        return number

    return read


def _duration_reader(path: str) -> Callable[[Any, BlobSink], int]:
    check = _int_reader(path)
    return lambda value, blobs: check(int(value.sec) * NS + int(value.nanosec), blobs)


def _time_reader(path: str) -> Callable[[Any, BlobSink], int]:
    return _duration_reader(path)


def _range_reader(integers: bool, path: str) -> Callable[[Any, BlobSink], list[Any]]:
    element = _int_reader(path) if integers else _float_reader(path)

    def read(value: Any, blobs: BlobSink) -> list[Any]:
        low, high = (element(item, blobs) for item in value)
        if low > high:
            raise ConversionError(path, "low is above high")
        return [low, high]

    return read


class BindingRefused(Exception):
    """A binding that names an invalid topic, message type or template id."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason


MSGTYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/([a-z]+/)?[A-Za-z][A-Za-z0-9_]*")


class Bindings:
    """Which template records a topic or a message type; a topic binding wins over a type one.

    One small JSON file, replaced atomically on each change: bindings are few and rarely change,
    and an ingest reads them once when it starts.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._topics: dict[str, str] = {}
        self._msgtypes: dict[str, str] = {}
        if path.exists():
            document = json.loads(path.read_text())
            self._topics = dict(document["topics"])
            self._msgtypes = dict(document["msgtypes"])

    def to_json(self) -> dict[str, dict[str, str]]:
        with self._lock:
            return {"topics": dict(self._topics), "msgtypes": dict(self._msgtypes)}

    def resolve(self, topic: str, msgtype: str) -> str | None:
        with self._lock:
            return self._topics.get(record_topic(topic)) or self._msgtypes.get(msgtype)

    def bind(
        self, *, template_id: str, topic: str | None = None, msgtype: str | None = None
    ) -> None:
        """Bind a topic or a message type (exactly one) to ``template_id``."""
        check_binding(template_id=template_id, topic=topic, msgtype=msgtype)
        with self._lock:
            if len(self._topics) + len(self._msgtypes) >= MAX_BINDINGS:
                raise BindingRefused("bindings", f"at most {MAX_BINDINGS}")
            if topic is not None:
                self._topics[record_topic(topic)] = template_id
            else:
                assert msgtype is not None
                self._msgtypes[msgtype] = template_id
            self._save()

    def unbind(self, *, topic: str | None = None, msgtype: str | None = None) -> bool:
        with self._lock:
            table = self._topics if topic is not None else self._msgtypes
            key = record_topic(topic) if topic is not None else msgtype
            if key is None or key not in table:
                return False
            del table[key]
            self._save()
            return True

    def _save(self) -> None:
        document = {"topics": self._topics, "msgtypes": self._msgtypes}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(self.path, json.dumps(document, sort_keys=True).encode())


def check_binding(*, template_id: str, topic: str | None, msgtype: str | None) -> None:
    if (topic is None) == (msgtype is None):
        raise BindingRefused("topic", "give exactly one of topic and msgtype")
    try:
        parse_template_id(template_id)
    except ValueError:
        raise BindingRefused(
            "template", f"{template_id[:300]!r} is not a template id name@version"
        ) from None
    if topic is not None and not recordable_topic(topic):
        raise BindingRefused("topic", f"{topic[:300]!r} is not a ROS topic name")
    if msgtype is not None and not MSGTYPE.fullmatch(msgtype):
        raise BindingRefused("msgtype", f"{msgtype[:300]!r} is not a ROS message type")
