"""A robot's share of a real cas: a pin past its pinned bytes is 507 ``quota_exceeded``
naming the robot and the figures, on every path that pins, and an upload past its new bytes
of the hour is 429 ``write_rate_exceeded`` with ``Retry-After``; either leaves the store as
it was. Removing a pin makes room, and other robots keep their own shares."""

from __future__ import annotations

import pytest

from robocloud.car import write_car
from robocloud.cas import Cas, PinShare
from robocloud.client import ServiceClient
from robocloud.errors import ApiError, RateLimitedError
from robocloud.identity import Identity
from robocloud.unixfs import ImportParams, import_bytes
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import (
    QUIET_GC,
    error_of,
    post_files,
    store_unchanged,
)
from tests.procs import ServiceProcess

SHARE = 10_000
WRITES = 30_000


@pytest.fixture
def cas_service(service_factory: ServiceFactory) -> ServiceProcess:
    return service_factory(
        "cas",
        {
            **QUIET_GC,
            "ROBOCLOUD_CAS_MAX_PINNED_BYTES_PER_ROBOT": str(SHARE),
            "ROBOCLOUD_CAS_MAX_WRITTEN_BYTES_PER_ROBOT_PER_HOUR": str(WRITES),
        },
    )


def refused(exc: pytest.ExceptionInfo[ApiError], robot: Identity, size: int, used: int) -> None:
    error = error_of(exc, 507, "quota_exceeded")
    assert error.details == {"robot": robot.address, "size": size, "used": used, "limit": SHARE}
    assert "pin/rm" in error.message


def test_every_path_that_pins_is_refused_past_the_share_with_nothing_stored(
    cas_service: ServiceProcess, identity: Identity
) -> None:
    with (
        Cas(cas_service.url, identity, retries=0) as cas,
        ServiceClient(cas_service.url, identity, retries=0) as signed,
    ):
        kept = cas.add_bytes(b"k" * 6_000)
        used = 6_000  # one raw block: the SDK adds with CIDv1 and raw leaves
        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            cas.add_bytes(b"a" * 5_000)
        refused(exc, identity, 5_000, used)

        blocks, root = import_bytes(b"c" * 5_000, ImportParams())
        car = b"".join(write_car([root], blocks))
        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            post_files(signed, "/api/v0/dag/import", ("more.car", car))
        refused(exc, identity, 5_000, used)

        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            post_files(signed, "/api/v0/block/put?pin=true", ("block", b"b" * 5_000))
        refused(exc, identity, 5_000, used)

        unpinned = cas.add_bytes(b"u" * 5_000, pin=False)
        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            cas.pin(unpinned)
        refused(exc, identity, 5_000, used)

        other = Identity.generate()
        with Cas(cas_service.url, other, retries=0) as theirs:
            theirs.pin(unpinned)
            assert cas.pins()[str(unpinned)]["Owners"] == [other.address]

        assert cas.pin_share() == PinShare(identity.address, used, SHARE, 11_000, WRITES)
        cas.unpin(kept)
        cas.pin(unpinned)
        assert cas.pin_share() == PinShare(identity.address, 5_000, SHARE, 11_000, WRITES)
        assert sorted(cas.pins()[str(unpinned)]["Owners"]) == sorted(
            [identity.address, other.address]
        )


def test_pinning_unpinning_and_writing_again_is_bounded_by_the_hour(
    cas_service: ServiceProcess, identity: Identity
) -> None:
    """Each upload is unpinned before the next, so the pins stay within their share; the
    blocks stay until a collection past the grace period, and the hour's bound stops them."""
    with Cas(cas_service.url, identity, retries=0) as cas:
        for turn in range(3):
            cas.unpin(cas.add_bytes(bytes([turn]) * 9_000))
        again = cas.add_bytes(bytes([0]) * 9_000)  # stored already: no new bytes
        cas.unpin(again)
        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            cas.add_bytes(b"w" * 9_000, pin=False)
        error = error_of(exc, 429, "write_rate_exceeded")
        retry_after = error.details.pop("retry_after")
        assert error.details == {
            "robot": identity.address,
            "size": 9_000,
            "written": 27_000,
            "limit": WRITES,
        }
        assert 3000 < retry_after <= 3660
        assert isinstance(exc.value, RateLimitedError)
        other = Identity.generate()
        with Cas(cas_service.url, other, retries=0) as theirs:
            theirs.add_bytes(b"w" * 9_000, pin=False)
