"""robocloud.ledger's registration policy calls against real nodes (anvil and the service).

The module's deployment runs in the Approved mode from its first test on: every robot that
registers here asks, and the admin or a registrar decides.
"""

from __future__ import annotations

import pytest

from robocloud.ledger import Ledger, RegistrationMode, RevertError, Role
from robocloud.ledger.transactions import quantity
from tests.integration.robocloud.ledger.conftest import Deployment, LedgerFactory

METADATA = bytes.fromhex("01701220") + bytes(range(32))


@pytest.fixture(scope="module")
def approved(deployment: Deployment) -> Ledger:
    """The admin's Ledger, the Registry switched to the Approved mode for the module."""
    admin = deployment.admin
    if admin.registration_mode() is RegistrationMode.OPEN:
        admin.set_registration_mode(RegistrationMode.APPROVED)
    return admin


def address(ledger: Ledger) -> str:
    assert ledger.identity is not None
    return ledger.identity.address


def nonce(ledger: Ledger) -> int:
    return quantity(ledger.rpc.request("eth_getTransactionCount", [address(ledger), "latest"]))


def asks(new_robot: LedgerFactory) -> Ledger:
    """A funded robot that has asked to register."""
    robot = new_robot()
    robot.register(METADATA)
    return robot


def registrar(approved: Ledger, new_robot: LedgerFactory) -> Ledger:
    """A robot the admin admitted and granted the registrar role."""
    robot = asks(new_robot)
    approved.approve(address(robot))
    approved.grant_role(address(robot), Role.REGISTRAR)
    return robot


def test_only_the_admin_sets_the_mode(approved: Ledger, new_robot: LedgerFactory) -> None:
    assert approved.registration_mode() is RegistrationMode.APPROVED
    with pytest.raises(RevertError) as unchanged:
        approved.set_registration_mode(RegistrationMode.APPROVED)
    assert unchanged.value.reason == "Registry: registration mode unchanged"
    robot = new_robot()
    before = nonce(robot)
    with pytest.raises(RevertError) as stranger:
        robot.set_registration_mode(RegistrationMode.OPEN)
    assert stranger.value.reason == "Registry: caller is not the admin"
    assert nonce(robot) == before
    assert approved.registration_mode() is RegistrationMode.APPROVED


def test_a_request_waits_until_the_admin_approves(
    approved: Ledger, new_robot: LedgerFactory
) -> None:
    robot = asks(new_robot)
    record = robot.robot(address(robot))
    assert robot.is_pending(address(robot))
    assert (record.registered, record.is_active) == (False, False)
    with pytest.raises(RevertError) as again:
        robot.register(METADATA)
    assert again.value.reason == "Registry: registration already pending"

    receipt = approved.approve(address(robot))
    assert receipt.status == 1
    record = robot.robot(address(robot))
    assert not robot.is_pending(address(robot))
    assert (record.registered, record.is_active, record.metadata_cid) == (True, True, METADATA)
    block = robot.rpc.request("eth_getBlockByNumber", [hex(receipt.block_number), False])
    assert record.registered_at == quantity(block["timestamp"])
    with pytest.raises(RevertError) as twice:
        approved.approve(address(robot))
    assert twice.value.reason == "Registry: no pending registration"


def test_a_registrar_approves_and_rejects_until_its_role_is_revoked(
    approved: Ledger, new_robot: LedgerFactory
) -> None:
    vouching = registrar(approved, new_robot)
    assert vouching.has_role(address(vouching), Role.REGISTRAR)
    admitted, refused, waiting = asks(new_robot), asks(new_robot), asks(new_robot)
    vouching.approve(address(admitted))
    vouching.reject(address(refused))
    assert admitted.is_active(address(admitted))
    assert not refused.is_pending(address(refused))
    assert refused.robot(address(refused)).registered is False
    refused.register(METADATA)
    assert refused.is_pending(address(refused))

    approved.revoke_role(address(vouching), Role.REGISTRAR)
    with pytest.raises(RevertError) as revoked:
        vouching.approve(address(waiting))
    assert revoked.value.reason == "Registry: caller is not a registrar"
    assert waiting.is_pending(address(waiting))


def test_a_suspended_registrar_decides_nothing(approved: Ledger, new_robot: LedgerFactory) -> None:
    vouching = registrar(approved, new_robot)
    waiting = asks(new_robot)
    approved.set_suspended(address(vouching), True)
    with pytest.raises(RevertError) as suspended:
        vouching.reject(address(waiting))
    assert suspended.value.reason == "Registry: caller is not a registrar"
    approved.set_suspended(address(vouching), False)
    vouching.reject(address(waiting))
    assert not waiting.is_pending(address(waiting))


def test_robots_without_the_role_decide_nothing(approved: Ledger, new_robot: LedgerFactory) -> None:
    member = asks(new_robot)
    approved.approve(address(member))
    waiting = asks(new_robot)
    for decide in (member.approve, member.reject, waiting.approve):
        with pytest.raises(RevertError) as refused:
            decide(address(waiting))
        assert refused.value.reason == "Registry: caller is not a registrar"
    assert waiting.is_pending(address(waiting))
    with pytest.raises(RevertError) as unknown:
        approved.reject(address(new_robot(funded=False)))
    assert unknown.value.reason == "Registry: no pending registration"
    with pytest.raises(RevertError) as unregistered:
        approved.grant_role(address(waiting), Role.REGISTRAR)
    assert unregistered.value.reason == "Registry: account is not registered"
