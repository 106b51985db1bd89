"""The gateway's CAR parameters and the content paths it puts in headers, without a server."""

from __future__ import annotations

import re

import pytest

from robocloud.cid import CID
from services.cas.errors import ERRORS
from services.cas.gateway import AnyPath, car_params
from services.cas.listing import content_url
from services.cas.ranges import EntityBytes, InvalidEntityBytes
from services.cas.store import UnknownScope

ROOT = CID.from_block(b"root")


@pytest.mark.parametrize(
    ("value", "size", "span"),
    [
        ("0:*", 100, (0, 100)),
        ("10:19", 100, (10, 20)),
        ("-10:*", 100, (90, 100)),
        ("499:-1000", 2000, (499, 1001)),
        ("0:999", 100, (0, 100)),
        ("-500:*", 100, (0, 100)),
        ("50:-60", 100, (0, 0)),
        ("0:*", 0, (0, 0)),
    ],
)
def test_entity_bytes_within_a_file(value: str, size: int, span: tuple[int, int]) -> None:
    assert EntityBytes.parse(value).within(size) == span


@pytest.mark.parametrize("value", ["100:*", "-200:-150"])
def test_entity_bytes_wholly_outside_the_file(value: str) -> None:
    with pytest.raises(InvalidEntityBytes, match="outside the file of 100 bytes"):
        EntityBytes.parse(value).within(100)


@pytest.mark.parametrize(
    "value",
    [
        "",
        "zz",
        "0",
        "0-9",
        "0:",
        ":5",
        "1:2:3",
        "\r\nX-Evil: 1",
        "日",
        "٣:*",
        "0:٣",
        "+1:2",
        "1" * 20 + ":*",
        "10:5",
        "-1:-5",
        " 0:1",
    ],
)
def test_malformed_entity_bytes_are_400_naming_the_parameter(value: str) -> None:
    with pytest.raises(InvalidEntityBytes) as exc:
        EntityBytes.parse(value)
    error = ERRORS.to_service_error(exc.value)
    assert error is not None
    assert (error.status, error.code, error.details) == (
        400,
        "invalid_entity_bytes",
        {"field": "entity-bytes"},
    )


def test_entity_bytes_have_one_canonical_text() -> None:
    """The CAR's ``ETag`` carries it: ``00:010`` and ``0:10`` are the same request."""
    assert str(EntityBytes.parse("00:010")) == str(EntityBytes.parse("0:10")) == "0:10"
    assert str(EntityBytes.parse("-0005:*")) == "-5:*"


def test_car_params_check_the_scope_and_let_a_range_imply_entity() -> None:
    assert car_params("block", None) == ("block", None)
    assert car_params("all", "0:*") == ("entity", EntityBytes(0, None))
    with pytest.raises(UnknownScope):
        car_params("bogus", None)
    with pytest.raises(UnknownScope):
        car_params("bogus", "0:*")
    with pytest.raises(InvalidEntityBytes):
        car_params("all", "zz")


def test_content_url_encodes_every_segment_for_headers() -> None:
    names = ["日本.txt", "a?b", "c#d", "50%off", "a/b", "a\r\nX: 1", "with space"]
    url = content_url(ROOT, names)
    assert url == (
        f"/ipfs/{ROOT}/%E6%97%A5%E6%9C%AC.txt/a%3Fb/c%23d/50%25off/a%2Fb/a%0D%0AX%3A%201/with%20space"
    )
    assert content_url(ROOT, []) == f"/ipfs/{ROOT}"


def test_the_path_convertor_matches_newlines() -> None:
    """Starlette's own ``path`` convertor (``.*``) stops at the first ``\\n``."""
    assert re.fullmatch(AnyPath.regex, "a\nb\r\nc") is not None
