"""A robot's share of pinned bytes, through a real cas: a pin past it is 507
``quota_exceeded`` naming the robot and the figures, on every path that pins, and leaves the
store as it was; removing a pin makes room, and other robots keep their own shares."""

from __future__ import annotations

import pytest

from robocloud.car import write_car
from robocloud.cas import Cas, PinShare
from robocloud.client import ServiceClient
from robocloud.errors import ApiError
from robocloud.identity import Identity
from robocloud.unixfs import ImportParams, import_bytes
from tests.conftest import ServiceFactory
from tests.integration.services.cas.conftest import (
    QUIET_GC,
    error_of,
    multipart,
    store_unchanged,
)
from tests.procs import ServiceProcess

SHARE = 10_000


@pytest.fixture
def cas_service(service_factory: ServiceFactory) -> ServiceProcess:
    return service_factory(
        "cas", {**QUIET_GC, "ROBOCLOUD_CAS_MAX_PINNED_BYTES_PER_ROBOT": str(SHARE)}
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
        body, content_type = multipart(("more.car", b"".join(write_car([root], blocks))))
        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            signed.request(
                "POST", "/api/v0/dag/import", content=body, headers={"Content-Type": content_type}
            )
        refused(exc, identity, 5_000, used)

        body, content_type = multipart(("block", b"b" * 5_000))
        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            signed.request(
                "POST",
                "/api/v0/block/put?pin=true",
                content=body,
                headers={"Content-Type": content_type},
            )
        refused(exc, identity, 5_000, used)

        unpinned = cas.add_bytes(b"u" * 5_000, pin=False)
        with store_unchanged(cas_service), pytest.raises(ApiError) as exc:
            cas.pin(unpinned)
        refused(exc, identity, 5_000, used)

        other = Identity.generate()
        with Cas(cas_service.url, other, retries=0) as theirs:
            theirs.pin(unpinned)
            assert cas.pins()[str(unpinned)]["Owners"] == [other.address]

        assert cas.pin_share() == PinShare(identity.address, used, SHARE)
        cas.unpin(kept)
        cas.pin(unpinned)
        assert cas.pin_share() == PinShare(identity.address, 5_000, SHARE)
        assert sorted(cas.pins()[str(unpinned)]["Owners"]) == sorted(
            [identity.address, other.address]
        )
