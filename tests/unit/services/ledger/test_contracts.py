"""Whether the ledger switches the Registry's registration mode at start, or refuses to start."""

from __future__ import annotations

import pytest

from robocloud.ledger.models import RegistrationMode
from services.ledger.contracts import RegistrationModeConflict, must_switch_mode

REGISTRY = "0x5FbDB2315678afecb367f032d93F642f64180aa3"
ADMIN = "0xf39Fd6e51aad88F6F4ce6aB8827279cffFb92266"
OTHER = "0x70997970C51812dc3A010C7d01b50e0d17dc79C8"
OPEN, APPROVED = RegistrationMode.OPEN, RegistrationMode.APPROVED


@pytest.mark.parametrize("operator", [ADMIN, OTHER, None])
def test_a_registry_already_in_the_mode_needs_nothing(operator: str | None) -> None:
    assert must_switch_mode(REGISTRY, APPROVED, APPROVED, ADMIN, operator) is False
    assert must_switch_mode(REGISTRY, OPEN, OPEN, ADMIN, operator) is False


@pytest.mark.parametrize("operator", [ADMIN, ADMIN.lower()])
def test_the_admin_key_switches_it(operator: str) -> None:
    assert must_switch_mode(REGISTRY, OPEN, APPROVED, ADMIN, operator) is True
    assert must_switch_mode(REGISTRY, APPROVED, OPEN, ADMIN, operator) is True


@pytest.mark.parametrize("operator", [OTHER, None])
def test_without_the_admin_key_a_different_mode_stops_the_start(operator: str | None) -> None:
    with pytest.raises(RegistrationModeConflict) as conflict:
        must_switch_mode(REGISTRY, APPROVED, OPEN, ADMIN, operator)
    assert (conflict.value.registry, conflict.value.current, conflict.value.wanted) == (
        REGISTRY,
        APPROVED,
        OPEN,
    )
    message = str(conflict.value)
    assert f"the Registry at {REGISTRY} is in the approved registration mode" in message
    assert "ROBOCLOUD_LEDGER_REGISTRATION_MODE is open" in message
    assert "robocloud admin mode open" in message
