"""``pin/share`` answers as the SDK reads them: a gateway's answer of another shape is no
share, never a robot with a negative or fractional count of bytes."""

from __future__ import annotations

from typing import Any

import pytest

from robocloud.cas import PinShare

ROBOT = "0x" + "a1" * 20


ANSWER = {
    "Robot": ROBOT,
    "PinnedBytes": 11,
    "MaxBytes": 1024,
    "WrittenBytesLastHour": 20,
    "MaxWrittenBytesPerHour": 2048,
}


def test_a_share_and_an_unbounded_one_are_read() -> None:
    assert PinShare.from_answer(ANSWER) == PinShare(ROBOT, 11, 1024, 20, 2048)
    unbounded = ANSWER | {"MaxBytes": None, "MaxWrittenBytesPerHour": None}
    assert PinShare.from_answer(unbounded) == PinShare(ROBOT, 11, None, 20, None)


@pytest.mark.parametrize(
    "answer",
    [
        list(ANSWER.values()),
        {key: value for key, value in ANSWER.items() if key != "PinnedBytes"},
        {key: value for key, value in ANSWER.items() if key != "WrittenBytesLastHour"},
        ANSWER | {"Robot": 7},
        ANSWER | {"PinnedBytes": -1},
        ANSWER | {"PinnedBytes": 1.5},
        ANSWER | {"WrittenBytesLastHour": True},
        ANSWER | {"MaxBytes": "lots"},
        ANSWER | {"MaxWrittenBytesPerHour": -5},
    ],
)
def test_an_answer_of_another_shape_is_no_share(answer: Any) -> None:
    assert PinShare.from_answer(answer) is None
