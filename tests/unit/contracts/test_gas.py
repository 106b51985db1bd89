"""Gas ceilings for the calls robots make often: a regression here costs every robot."""

from __future__ import annotations

from tests.unit.contracts.chain import Chain

CID = bytes.fromhex("01551220") + bytes(range(32))
DESCRIPTION = bytes.fromhex("01711220") + bytes(range(32, 64))


def test_common_calls_stay_cheap(chain: Chain, storage_node: str) -> None:
    registry, anchor_log = chain.registry.functions, chain.anchor_log.functions
    used = {
        "register": chain.send(registry.register(CID), chain.robot)["gasUsed"],
        "advertise (first)": chain.send(registry.advertise(CID, DESCRIPTION), chain.robot)[
            "gasUsed"
        ],
        "advertise (repeat)": chain.send(registry.advertise(CID, b""), chain.robot)["gasUsed"],
        "anchor": chain.send(anchor_log.anchor(1, b"\x01" * 32, 10), storage_node)["gasUsed"],
    }
    print(used)
    ceilings = {
        "register": 160_000,
        "advertise (first)": 170_000,
        "advertise (repeat)": 50_000,
        "anchor": 120_000,
    }
    for call, gas in used.items():
        assert gas <= ceilings[call], f"{call} uses {gas} gas"


def test_the_approved_mode_stays_cheap(chain: Chain) -> None:
    """A request costs what a registration did; a registrar's decision costs far less."""
    registry = chain.registry.functions
    chain.send(registry.setRegistrationMode(1), chain.admin)
    chain.send(registry.register(CID), chain.node)
    chain.send(registry.approve(chain.node), chain.admin)
    chain.send(registry.grantRole(chain.node, registry.REGISTRAR().call()), chain.admin)
    used = {
        "register (request)": chain.send(registry.register(CID), chain.robot)["gasUsed"],
        "approve (registrar)": chain.send(registry.approve(chain.robot), chain.node)["gasUsed"],
    }
    chain.send(registry.register(CID), chain.other)
    used["reject (admin)"] = chain.send(registry.reject(chain.other), chain.admin)["gasUsed"]
    print(used)
    ceilings = {
        "register (request)": 160_000,
        "approve (registrar)": 80_000,
        "reject (admin)": 60_000,
    }
    for call, gas in used.items():
        assert gas <= ceilings[call], f"{call} uses {gas} gas"
