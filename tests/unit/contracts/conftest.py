"""Deployed Registry and AnchorLog on a fresh in-process eth-tester chain per test."""

from __future__ import annotations

import pytest

from tests.unit.contracts.chain import Chain, new_chain


@pytest.fixture
def chain() -> Chain:
    return new_chain()


@pytest.fixture
def storage_node(chain: Chain) -> str:
    """`chain.node` registered and granted the storage-node role."""
    chain.send(chain.registry.functions.register(b"\x01node-metadata"), chain.node)
    role = chain.registry.functions.STORAGE_NODE().call()
    chain.send(chain.registry.functions.grantRole(chain.node, role), chain.admin)
    return chain.node
