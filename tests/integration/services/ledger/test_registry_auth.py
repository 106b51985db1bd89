"""``ROBOCLOUD_AUTH=registered``: other services let in registered, active robots only."""

from __future__ import annotations

from contextlib import closing

import anyio
import pytest

from robocloud.cas import Cas
from robocloud.client import ServiceClient
from robocloud.errors import ApiError, PermissionDeniedError
from robocloud.identity import Identity
from robocloud.ledger import Role
from robocloud.storage import Storage
from services.common.errors import Forbidden, Unavailable
from services.common.registry_auth import RegistryAuthorizer
from tests.conftest import ServiceFactory
from tests.integration.services.ledger.conftest import RobotFactory, Service
from tests.procs import free_port


def test_registered_robot_writes_and_unregistered_is_403(
    service: Service, robot: RobotFactory, service_factory: ServiceFactory
) -> None:
    storage = service_factory(
        "storage", {"ROBOCLOUD_AUTH": "registered", "ROBOCLOUD_LEDGER_URL": service.url}
    )
    registered = robot()
    assert registered.identity is not None
    with ServiceClient(storage.url, registered.identity) as client:
        answer = client.post_json("/v1/whoami")
    assert (answer["address"], answer["auth"]) == (registered.identity.address, "registered")

    stranger = Identity.generate()
    with (
        ServiceClient(storage.url, stranger) as client,
        pytest.raises(PermissionDeniedError) as denied,
    ):
        client.post_json("/v1/whoami")
    assert denied.value.code == "address_not_allowed"
    assert denied.value.details == {"address": stranger.address}


def test_roles_and_deactivation_are_checked(service: Service, robot: RobotFactory) -> None:
    node = robot()
    assert node.identity is not None
    address = node.identity.address
    authorizer = RegistryAuthorizer(service.url, cache_s=0, negative_cache_s=0)

    async def check(role: str | None = None) -> None:
        await authorizer.authorize(address, role)

    with closing(authorizer):
        anyio.run(check)
        with pytest.raises(Forbidden) as denied:
            anyio.run(check, "storage_node")
        assert denied.value.code == "role_required"
        assert not anyio.run(authorizer.holds_role, address, "storage_node")
        service.admin.grant_role(address, Role.STORAGE_NODE)
        anyio.run(check, "storage_node")
        assert anyio.run(authorizer.holds_role, address, "storage_node")
        node.deactivate()
        with pytest.raises(Forbidden) as denied:
            anyio.run(check)
        assert not anyio.run(authorizer.holds_role, address, "storage_node")
    assert denied.value.code == "robot_inactive"


def test_allowed_addresses_skip_the_ledger_and_an_unreachable_ledger_is_503() -> None:
    allowed = Identity.generate().address
    authorizer = RegistryAuthorizer(f"http://127.0.0.1:{free_port()}", [allowed], timeout_s=1)
    with closing(authorizer):
        anyio.run(authorizer.authorize, allowed)
        assert anyio.run(authorizer.holds_role, allowed, "storage_node")
        with pytest.raises(Unavailable) as unavailable:
            anyio.run(authorizer.authorize, Identity.generate().address)
    assert unavailable.value.code == "ledger_unreachable"


def test_only_a_reviewer_approves_a_template(
    service: Service, robot: RobotFactory, service_factory: ServiceFactory
) -> None:
    storage = service_factory(
        "storage",
        {
            "ROBOCLOUD_AUTH": "registered",
            "ROBOCLOUD_LEDGER_URL": service.url,
            "ROBOCLOUD_STORAGE_ANCHOR": "false",
            "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
        },
    )
    designer, reviewer = robot(), robot()
    assert designer.identity is not None
    assert reviewer.identity is not None
    document = {"name": "dock_state", "version": 1, "fields": {"state": "string"}}
    with Storage(storage.url, designer.identity) as client:
        client.create_template(document)
        client.submit_template("dock_state@1")
        with pytest.raises(PermissionDeniedError) as denied:
            client.review_template("dock_state@1", "approve", "my own")
        assert denied.value.code == "role_required"
        assert denied.value.details == {"address": designer.identity.address, "role": "reviewer"}
        assert client.template("dock_state@1").status == "submitted"
    service.admin.grant_role(reviewer.identity.address, Role.REVIEWER)
    with Storage(storage.url, reviewer.identity) as client:
        approved = client.review_template("dock_state@1", "approve", "looks right")
    assert (approved.status, approved.reviewer) == ("approved", reviewer.identity.address)


def test_a_storage_node_pins_past_the_share_that_bounds_other_robots(
    service: Service, robot: RobotFactory, service_factory: ServiceFactory
) -> None:
    """The storage node pins every robot's bags under its own key: its pins are unbounded,
    while a robot without the role is held to ``ROBOCLOUD_CAS_MAX_PINNED_BYTES_PER_ROBOT``."""
    cas_service = service_factory(
        "cas",
        {
            "ROBOCLOUD_AUTH": "registered",
            "ROBOCLOUD_LEDGER_URL": service.url,
            "ROBOCLOUD_CAS_MAX_PINNED_BYTES_PER_ROBOT": "1000",
        },
    )
    node, other = robot(), robot()
    assert node.identity is not None
    assert other.identity is not None
    service.admin.grant_role(node.identity.address, Role.STORAGE_NODE)
    with Cas(cas_service.url, node.identity, retries=0) as cas:
        bag = cas.add_bytes(b"b" * 5_000)
    with Cas(cas_service.url, other.identity, retries=0) as cas:
        with pytest.raises(ApiError) as exc:
            cas.add_bytes(b"o" * 5_000)
        assert (exc.value.status, exc.value.code) == (507, "quota_exceeded")
        assert exc.value.details["robot"] == other.identity.address
        assert list(cas.pins()) == [str(bag)]
