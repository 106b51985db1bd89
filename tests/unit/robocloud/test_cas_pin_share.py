"""``pin/share`` answers as the SDK reads them: a gateway's answer of another shape is no
share, never a robot with a negative or fractional count of bytes."""

from __future__ import annotations

from typing import Any

import pytest

from robocloud.cas import PinShare

ROBOT = "0x" + "a1" * 20


def test_a_share_and_an_unbounded_one_are_read() -> None:
    answer = {"Robot": ROBOT, "PinnedBytes": 11, "MaxBytes": 1024}
    assert PinShare.from_answer(answer) == PinShare(ROBOT, 11, 1024)
    assert PinShare.from_answer(answer | {"MaxBytes": None}) == PinShare(ROBOT, 11, None)


@pytest.mark.parametrize(
    "answer",
    [
        [ROBOT, 11, 1024],
        {"Robot": ROBOT, "MaxBytes": 1024},
        {"Robot": 7, "PinnedBytes": 11, "MaxBytes": 1024},
        {"Robot": ROBOT, "PinnedBytes": -1, "MaxBytes": 1024},
        {"Robot": ROBOT, "PinnedBytes": 1.5, "MaxBytes": 1024},
        {"Robot": ROBOT, "PinnedBytes": True, "MaxBytes": 1024},
        {"Robot": ROBOT, "PinnedBytes": 11, "MaxBytes": "lots"},
    ],
)
def test_an_answer_of_another_shape_is_no_share(answer: Any) -> None:
    assert PinShare.from_answer(answer) is None
