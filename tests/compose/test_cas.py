"""cas in Compose: a file put through the published port survives a restart, verified."""

from __future__ import annotations

import os

import httpx
import pytest

from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.unixfs import import_bytes
from tests.compose.deployment import Deployment

pytestmark = pytest.mark.compose


def test_put_restart_get(deployment: Deployment) -> None:
    data = os.urandom(700_000)
    _, expected = import_bytes(data)
    with Cas(deployment.urls["cas"], deployment.identity, timeout=30) as cas:
        assert cas.add_bytes(data) == expected
    deployment.restart(["cas"])
    with Cas(deployment.urls["cas"], deployment.identity, timeout=30) as cas:
        assert cas.get(expected) == data
        assert cas.pins()[str(expected)]["Owners"] == [deployment.identity.address]
    raw = httpx.get(f"{deployment.urls['cas']}/ipfs/{expected}?format=raw", timeout=10)
    CID.decode(str(expected)).verify(raw.content)
