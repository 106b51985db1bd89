"""Compare what robocloud decodes from a bag with rosbags' own deserialised messages."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Collection, Iterator
from typing import Any

import numpy as np

from services.storage.bags import Bag


def decoded(bag: Bag, topics: Collection[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """``(topic, t_ns, plain message)`` in time order, decoded as staging decodes them
    (:meth:`Bag.deserialize`), so a connection without a usable definition raises there."""
    for connection, t_ns, raw in bag.raw_messages(topics):
        yield connection.topic, t_ns, plain(bag.deserialize(connection, t_ns, raw))


def plain(message: Any) -> Any:
    """A rosbags message as dicts, lists and scalars; ``bytes`` for an array of one-byte items."""
    if dataclasses.is_dataclass(message) and not isinstance(message, type):
        return {name: plain(getattr(message, name)) for name in _data_fields(message)}
    if isinstance(message, np.ndarray):
        return message.tobytes() if message.itemsize == 1 else message.tolist()
    if isinstance(message, list):
        return [plain(item) for item in message]
    return message


def _data_fields(message: Any) -> list[str]:
    """A message's data fields: constants (upper-case class fields) are not data."""
    return [
        f.name
        for f in dataclasses.fields(message)
        if not f.name.startswith("__") and not f.name.isupper()
    ]


def assert_matches_rosbags(plain: Any, message: Any, path: str = "") -> None:
    """``plain`` (dicts, lists, bytes) holds exactly the values of rosbags' ``message``.

    Constants (upper-case class fields) are not message data and are not compared.
    """
    if dataclasses.is_dataclass(message):
        names = _data_fields(message)
        assert isinstance(plain, dict), path
        assert list(plain) == names, path
        for name in names:
            assert_matches_rosbags(plain[name], getattr(message, name), f"{path}.{name}")
    elif isinstance(message, np.ndarray):
        if isinstance(plain, bytes):
            assert message.itemsize == 1, path
            assert plain == message.tobytes(), path
        else:
            assert_matches_rosbags(plain, message.tolist(), path)
    elif isinstance(message, list):
        assert isinstance(plain, list), path
        assert len(plain) == len(message), path
        for index, (left, right) in enumerate(zip(plain, message, strict=True)):
            assert_matches_rosbags(left, right, f"{path}[{index}]")
    elif isinstance(message, float) and math.isnan(message):
        assert isinstance(plain, float), path
        assert math.isnan(plain), path
    else:
        assert plain == message, path
        assert type(plain) is type(message) or isinstance(message, np.generic), path
