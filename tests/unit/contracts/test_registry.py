"""Registry: registration, roles, suspension and advertisements, every revert reason."""

from __future__ import annotations

from web3 import Web3

from tests.unit.contracts.chain import Chain

CID = bytes.fromhex("01551220") + bytes(range(32))
DESCRIPTION = bytes.fromhex("01711220") + bytes(range(32, 64))
METADATA = bytes.fromhex("01701220") + bytes(32)
MAX_CID = 128
NOT_REGISTERED = "Registry: account is not registered"


def role(chain: Chain, name: str) -> bytes:
    value: bytes = getattr(chain.registry.functions, name)().call()
    return value


def register(chain: Chain, account: str, metadata: bytes = METADATA) -> None:
    chain.send(chain.registry.functions.register(metadata), account)


def robot_record(chain: Chain, account: str) -> list[object]:
    record: list[object] = chain.registry.functions.getRobot(account).call()
    return record


# ----- registration -----


def test_register_stores_the_record_and_emits(chain: Chain) -> None:
    receipt = chain.send(chain.registry.functions.register(METADATA), chain.robot)
    ts = chain.timestamp(receipt)
    assert robot_record(chain, chain.robot) == [METADATA, ts, True, True, False]
    assert chain.registry.functions.isRegistered(chain.robot).call()
    assert chain.registry.functions.isActive(chain.robot).call()
    assert chain.registry.functions.robotCount().call() == 1
    assert chain.events(chain.registry, "RobotRegistered", receipt) == [
        {"robot": chain.robot, "metadataCid": METADATA, "timestamp": ts}
    ]


def test_unknown_account_reads_as_empty(chain: Chain) -> None:
    assert robot_record(chain, chain.other) == [b"", 0, False, False, False]
    assert not chain.registry.functions.isActive(chain.other).call()


def test_register_rejects_empty_metadata(chain: Chain) -> None:
    chain.assert_reverts(
        chain.registry.functions.register(b""), chain.robot, "Registry: empty metadata CID"
    )
    assert robot_record(chain, chain.robot) == [b"", 0, False, False, False]
    assert chain.registry.functions.robotCount().call() == 0


def test_register_rejects_overlong_metadata(chain: Chain) -> None:
    chain.send(chain.registry.functions.register(b"\x01" * MAX_CID), chain.other)
    chain.assert_reverts(
        chain.registry.functions.register(b"\x01" * (MAX_CID + 1)),
        chain.robot,
        "Registry: CID too long",
    )
    assert not chain.registry.functions.isRegistered(chain.robot).call()


def test_register_twice_is_rejected(chain: Chain) -> None:
    register(chain, chain.robot)
    chain.assert_reverts(
        chain.registry.functions.register(b"\x02other"), chain.robot, "Registry: already registered"
    )
    assert robot_record(chain, chain.robot)[0] == METADATA
    assert chain.registry.functions.robotCount().call() == 1


def test_update_metadata(chain: Chain) -> None:
    register(chain, chain.robot)
    receipt = chain.send(chain.registry.functions.updateMetadata(b"\x02new"), chain.robot)
    assert robot_record(chain, chain.robot)[0] == b"\x02new"
    assert chain.events(chain.registry, "MetadataUpdated", receipt) == [
        {"robot": chain.robot, "metadataCid": b"\x02new"}
    ]


def test_update_metadata_rejects_bad_input(chain: Chain) -> None:
    update = chain.registry.functions.updateMetadata
    chain.assert_reverts(update(b"\x02new"), chain.robot, "Registry: caller is not registered")
    register(chain, chain.robot)
    chain.assert_reverts(update(b""), chain.robot, "Registry: empty metadata CID")
    chain.assert_reverts(update(b"\x01" * (MAX_CID + 1)), chain.robot, "Registry: CID too long")
    assert robot_record(chain, chain.robot)[0] == METADATA


# ----- activation and suspension -----


def test_deactivate_and_reactivate(chain: Chain) -> None:
    register(chain, chain.robot)
    off = chain.send(chain.registry.functions.deactivate(), chain.robot)
    assert not chain.registry.functions.isActive(chain.robot).call()
    assert robot_record(chain, chain.robot)[2:] == [True, False, False]
    on = chain.send(chain.registry.functions.reactivate(), chain.robot)
    assert chain.registry.functions.isActive(chain.robot).call()
    assert chain.events(chain.registry, "RobotActivationChanged", off) == [
        {"robot": chain.robot, "active": False}
    ]
    assert chain.events(chain.registry, "RobotActivationChanged", on) == [
        {"robot": chain.robot, "active": True}
    ]


def test_activation_reverts(chain: Chain) -> None:
    functions = chain.registry.functions
    not_registered = "Registry: caller is not registered"
    chain.assert_reverts(functions.deactivate(), chain.robot, not_registered)
    chain.assert_reverts(functions.reactivate(), chain.robot, not_registered)
    register(chain, chain.robot)
    chain.assert_reverts(functions.reactivate(), chain.robot, "Registry: already active")
    chain.send(functions.deactivate(), chain.robot)
    chain.assert_reverts(functions.deactivate(), chain.robot, "Registry: already inactive")
    assert robot_record(chain, chain.robot)[2:] == [True, False, False]


def test_admin_suspends_and_restores(chain: Chain) -> None:
    register(chain, chain.robot)
    receipt = chain.send(chain.registry.functions.setSuspended(chain.robot, True), chain.admin)
    assert not chain.registry.functions.isActive(chain.robot).call()
    assert robot_record(chain, chain.robot)[2:] == [True, True, True]
    assert chain.events(chain.registry, "RobotSuspensionChanged", receipt) == [
        {"robot": chain.robot, "suspended": True}
    ]
    chain.send(chain.registry.functions.setSuspended(chain.robot, False), chain.admin)
    assert chain.registry.functions.isActive(chain.robot).call()


def test_suspended_robot_cannot_lift_its_suspension_by_reactivating(chain: Chain) -> None:
    register(chain, chain.robot)
    chain.send(chain.registry.functions.setSuspended(chain.robot, True), chain.admin)
    chain.send(chain.registry.functions.deactivate(), chain.robot)
    chain.send(chain.registry.functions.reactivate(), chain.robot)
    assert not chain.registry.functions.isActive(chain.robot).call()


def test_suspension_reverts(chain: Chain) -> None:
    suspend = chain.registry.functions.setSuspended
    not_admin = "Registry: caller is not the admin"
    chain.assert_reverts(suspend(chain.robot, True), chain.admin, NOT_REGISTERED)
    register(chain, chain.robot)
    chain.assert_reverts(suspend(chain.robot, True), chain.other, not_admin)
    chain.assert_reverts(suspend(chain.robot, True), chain.robot, not_admin)
    chain.assert_reverts(suspend(chain.robot, False), chain.admin, "Registry: suspension unchanged")
    assert chain.registry.functions.isActive(chain.robot).call()


# ----- roles and admin -----


def test_role_ids_are_the_documented_hashes(chain: Chain) -> None:
    for name, label in [
        ("STORAGE_NODE", "storage_node"),
        ("REVIEWER", "reviewer"),
        ("AGGREGATOR", "aggregator"),
        ("REGISTRAR", "registrar"),
    ]:
        assert role(chain, name) == Web3.keccak(text=f"robocloud.role.{label}")


def test_grant_and_revoke_roles(chain: Chain) -> None:
    register(chain, chain.robot)
    reviewer = role(chain, "REVIEWER")
    granted = chain.send(chain.registry.functions.grantRole(chain.robot, reviewer), chain.admin)
    assert chain.registry.functions.hasRole(chain.robot, reviewer).call()
    assert chain.registry.functions.isActiveWithRole(chain.robot, reviewer).call()
    assert not chain.registry.functions.hasRole(chain.robot, role(chain, "AGGREGATOR")).call()
    assert chain.events(chain.registry, "RoleGranted", granted) == [
        {"role": reviewer, "account": chain.robot}
    ]
    chain.send(chain.registry.functions.deactivate(), chain.robot)
    assert chain.registry.functions.hasRole(chain.robot, reviewer).call()
    assert not chain.registry.functions.isActiveWithRole(chain.robot, reviewer).call()
    revoked = chain.send(chain.registry.functions.revokeRole(chain.robot, reviewer), chain.admin)
    assert not chain.registry.functions.hasRole(chain.robot, reviewer).call()
    assert chain.events(chain.registry, "RoleRevoked", revoked) == [
        {"role": reviewer, "account": chain.robot}
    ]


def test_role_reverts(chain: Chain) -> None:
    functions = chain.registry.functions
    storage = role(chain, "STORAGE_NODE")
    unknown = Web3.keccak(text="robocloud.role.emperor")
    chain.assert_reverts(functions.grantRole(chain.robot, storage), chain.admin, NOT_REGISTERED)
    register(chain, chain.robot)
    not_admin = "Registry: caller is not the admin"
    chain.assert_reverts(functions.grantRole(chain.robot, storage), chain.robot, not_admin)
    chain.assert_reverts(functions.revokeRole(chain.robot, storage), chain.other, not_admin)
    chain.assert_reverts(
        functions.grantRole(chain.robot, unknown), chain.admin, "Registry: unknown role"
    )
    chain.assert_reverts(
        functions.revokeRole(chain.robot, unknown), chain.admin, "Registry: unknown role"
    )
    chain.assert_reverts(
        functions.revokeRole(chain.robot, storage), chain.admin, "Registry: role not granted"
    )
    chain.send(functions.grantRole(chain.robot, storage), chain.admin)
    chain.assert_reverts(
        functions.grantRole(chain.robot, storage), chain.admin, "Registry: role already granted"
    )
    assert functions.hasRole(chain.robot, storage).call()
    assert not functions.hasRole(chain.robot, unknown).call()


def test_transfer_admin(chain: Chain) -> None:
    functions = chain.registry.functions
    assert functions.admin().call() == chain.admin
    receipt = chain.send(functions.transferAdmin(chain.other), chain.admin)
    assert functions.admin().call() == chain.other
    assert chain.events(chain.registry, "AdminTransferred", receipt) == [
        {"previousAdmin": chain.admin, "newAdmin": chain.other}
    ]
    register(chain, chain.robot)
    chain.assert_reverts(
        functions.setSuspended(chain.robot, True), chain.admin, "Registry: caller is not the admin"
    )
    chain.send(functions.setSuspended(chain.robot, True), chain.other)


def test_transfer_admin_reverts(chain: Chain) -> None:
    functions = chain.registry.functions
    zero = "0x" + "00" * 20
    chain.assert_reverts(
        functions.transferAdmin(chain.other), chain.robot, "Registry: caller is not the admin"
    )
    chain.assert_reverts(
        functions.transferAdmin(zero), chain.admin, "Registry: new admin is the zero address"
    )
    assert functions.admin().call() == chain.admin


# ----- advertisements -----


def advertisement(chain: Chain, cid: bytes) -> list[object]:
    record: list[object] = chain.registry.functions.getAdvertisement(cid).call()
    return record


def test_first_advertiser_is_kept_and_every_advertisement_logged(chain: Chain) -> None:
    register(chain, chain.robot)
    register(chain, chain.other)
    first = chain.send(chain.registry.functions.advertise(CID, DESCRIPTION), chain.robot)
    second = chain.send(chain.registry.functions.advertise(CID, b""), chain.other)
    ts = chain.timestamp(first)
    assert advertisement(chain, CID) == [chain.robot, ts, first["blockNumber"], 2, DESCRIPTION]
    cid_hash = Web3.keccak(CID)
    assert chain.events(chain.registry, "Advertised", first) == [
        {
            "cidHash": cid_hash,
            "advertiser": chain.robot,
            "cid": CID,
            "descriptionCid": DESCRIPTION,
            "first": True,
            "timestamp": ts,
        }
    ]
    assert chain.events(chain.registry, "Advertised", second) == [
        {
            "cidHash": cid_hash,
            "advertiser": chain.other,
            "cid": CID,
            "descriptionCid": b"",
            "first": False,
            "timestamp": chain.timestamp(second),
        }
    ]


def test_unadvertised_cid_reads_as_empty(chain: Chain) -> None:
    assert advertisement(chain, CID) == ["0x" + "00" * 20, 0, 0, 0, b""]


def test_only_active_robots_advertise(chain: Chain) -> None:
    advertise = chain.registry.functions.advertise(CID, DESCRIPTION)
    reason = "Registry: advertiser is not an active robot"
    chain.assert_reverts(advertise, chain.robot, reason)
    register(chain, chain.robot)
    chain.send(chain.registry.functions.deactivate(), chain.robot)
    chain.assert_reverts(advertise, chain.robot, reason)
    chain.send(chain.registry.functions.reactivate(), chain.robot)
    chain.send(chain.registry.functions.setSuspended(chain.robot, True), chain.admin)
    chain.assert_reverts(advertise, chain.robot, reason)
    assert advertisement(chain, CID)[3] == 0


def test_advertise_rejects_bad_cids(chain: Chain) -> None:
    register(chain, chain.robot)
    advertise = chain.registry.functions.advertise
    too_long = b"\x01" * (MAX_CID + 1)
    chain.assert_reverts(advertise(b"", DESCRIPTION), chain.robot, "Registry: empty CID")
    chain.assert_reverts(advertise(too_long, DESCRIPTION), chain.robot, "Registry: CID too long")
    chain.assert_reverts(advertise(CID, too_long), chain.robot, "Registry: CID too long")
    assert advertisement(chain, CID)[3] == 0
    assert advertisement(chain, b"")[3] == 0
