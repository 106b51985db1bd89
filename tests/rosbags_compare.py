"""Compare plain values produced by robocloud with rosbags' own deserialised messages."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np


def assert_matches_rosbags(plain: Any, message: Any, path: str = "") -> None:
    """``plain`` (dicts, lists, bytes) holds exactly the values of rosbags' ``message``.

    Constants (upper-case class fields) are not message data and are not compared.
    """
    if dataclasses.is_dataclass(message):
        names = [
            f.name
            for f in dataclasses.fields(message)
            if not f.name.startswith("__") and not f.name.isupper()
        ]
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
