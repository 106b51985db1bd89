"""Registry registration modes: Open admits at once; Approved waits for a registrar."""

from __future__ import annotations

import pytest

from tests.unit.contracts.chain import Chain

METADATA = bytes.fromhex("01701220") + bytes(32)
OPEN, APPROVED = 0, 1
NOT_A_REGISTRAR = "Registry: caller is not a registrar"
NOTHING_PENDING = "Registry: no pending registration"


@pytest.fixture
def approved(chain: Chain) -> Chain:
    chain.send(chain.registry.functions.setRegistrationMode(APPROVED), chain.admin)
    return chain


def request(chain: Chain, account: str) -> object:
    return chain.send(chain.registry.functions.register(METADATA), account)


def state(chain: Chain, account: str) -> tuple[bool, bool, bool, int, int]:
    functions = chain.registry.functions
    return (
        functions.isRegistered(account).call(),
        functions.isPending(account).call(),
        functions.isActive(account).call(),
        functions.robotCount().call(),
        functions.pendingCount().call(),
    )


def registrar_role(chain: Chain) -> bytes:
    role: bytes = chain.registry.functions.REGISTRAR().call()
    return role


def test_the_mode_starts_open_and_only_the_admin_changes_it(chain: Chain) -> None:
    assert chain.registry.functions.registrationMode().call() == OPEN
    chain.assert_reverts(
        chain.registry.functions.setRegistrationMode(APPROVED),
        chain.robot,
        "Registry: caller is not the admin",
    )
    receipt = chain.send(chain.registry.functions.setRegistrationMode(APPROVED), chain.admin)
    assert chain.events(chain.registry, "RegistrationModeChanged", receipt) == [{"mode": APPROVED}]
    chain.assert_reverts(
        chain.registry.functions.setRegistrationMode(APPROVED),
        chain.admin,
        "Registry: registration mode unchanged",
    )


def test_a_registration_in_approved_mode_waits(approved: Chain) -> None:
    receipt = request(approved, approved.robot)
    assert state(approved, approved.robot) == (False, True, False, 0, 1)
    assert approved.events(approved.registry, "RobotRegistered", receipt) == []
    assert approved.events(approved.registry, "RegistrationRequested", receipt) == [
        {
            "robot": approved.robot,
            "metadataCid": METADATA,
            "timestamp": approved.timestamp(receipt),
        }
    ]
    approved.assert_reverts(
        approved.registry.functions.register(METADATA),
        approved.robot,
        "Registry: registration already pending",
    )
    approved.assert_reverts(
        approved.registry.functions.advertise(METADATA, b""),
        approved.robot,
        "Registry: advertiser is not an active robot",
    )


def test_the_admin_approves(approved: Chain) -> None:
    request(approved, approved.robot)
    approved.assert_reverts(
        approved.registry.functions.approve(approved.robot), approved.other, NOT_A_REGISTRAR
    )
    receipt = approved.send(approved.registry.functions.approve(approved.robot), approved.admin)
    assert state(approved, approved.robot) == (True, False, True, 1, 0)
    assert approved.events(approved.registry, "RegistrationApproved", receipt) == [
        {"robot": approved.robot, "registrar": approved.admin}
    ]
    assert approved.events(approved.registry, "RobotRegistered", receipt) == [
        {
            "robot": approved.robot,
            "metadataCid": METADATA,
            "timestamp": approved.timestamp(receipt),
        }
    ]
    approved.assert_reverts(
        approved.registry.functions.approve(approved.robot), approved.admin, NOTHING_PENDING
    )


def test_an_active_registrar_approves_and_rejects(approved: Chain) -> None:
    registrar = approved.node
    request(approved, registrar)
    approved.send(approved.registry.functions.approve(registrar), approved.admin)
    approved.send(
        approved.registry.functions.grantRole(registrar, registrar_role(approved)), approved.admin
    )
    request(approved, approved.robot)
    request(approved, approved.other)
    approved.send(approved.registry.functions.approve(approved.robot), registrar)
    receipt = approved.send(approved.registry.functions.reject(approved.other), registrar)
    assert approved.events(approved.registry, "RegistrationRejected", receipt) == [
        {"robot": approved.other, "registrar": registrar}
    ]
    assert state(approved, approved.robot) == (True, False, True, 2, 0)
    assert state(approved, approved.other) == (False, False, False, 2, 0)
    assert approved.registry.functions.getRobot(approved.other).call() == [
        b"",
        0,
        False,
        False,
        False,
    ]
    request(approved, approved.other)
    assert state(approved, approved.other)[1]


def test_a_suspended_or_deactivated_registrar_cannot_approve(approved: Chain) -> None:
    registrar = approved.node
    request(approved, registrar)
    approved.send(approved.registry.functions.approve(registrar), approved.admin)
    approved.send(
        approved.registry.functions.grantRole(registrar, registrar_role(approved)), approved.admin
    )
    request(approved, approved.robot)
    approved.send(approved.registry.functions.setSuspended(registrar, True), approved.admin)
    approved.assert_reverts(
        approved.registry.functions.approve(approved.robot), registrar, NOT_A_REGISTRAR
    )
    approved.send(approved.registry.functions.setSuspended(registrar, False), approved.admin)
    approved.send(approved.registry.functions.deactivate(), registrar)
    approved.assert_reverts(
        approved.registry.functions.reject(approved.robot), registrar, NOT_A_REGISTRAR
    )


def test_rejecting_nothing_and_by_strangers_is_refused(approved: Chain) -> None:
    approved.assert_reverts(
        approved.registry.functions.reject(approved.robot), approved.admin, NOTHING_PENDING
    )
    request(approved, approved.robot)
    approved.assert_reverts(
        approved.registry.functions.reject(approved.robot), approved.robot, NOT_A_REGISTRAR
    )
    assert state(approved, approved.robot) == (False, True, False, 0, 1)


def test_open_mode_admits_at_once_as_before(chain: Chain) -> None:
    receipt = request(chain, chain.robot)
    assert state(chain, chain.robot) == (True, False, True, 1, 0)
    assert chain.events(chain.registry, "RegistrationRequested", receipt) == []
