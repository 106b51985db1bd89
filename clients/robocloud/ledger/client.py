"""``Ledger``: register, advertise, anchor and read robocloud's contracts from a robot.

Everything goes through standard JSON-RPC with transactions signed locally, so a robot can
check what the ledger service tells it against any Ethereum node. The ledger service is needed
only to learn where the contracts are (``GET /v1/contracts``) and for the development faucet;
``LedgerService`` is the typed client of those REST routes (and of the index's reads).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import httpx
from eth_abi.exceptions import DecodingError
from eth_utils.address import is_address, to_checksum_address
from eth_utils.crypto import keccak

from robocloud.cid import parse_cid
from robocloud.client import MAX_WAIT_S, Closeable, ServiceClient
from robocloud.config import deployment_chain
from robocloud.errors import InvalidAnswerError, MissingIdentityError, NotFoundError
from robocloud.identity import Identity
from robocloud.ledger.abi import ContractAbi, DecodedLog, check_block
from robocloud.ledger.errors import (
    AddressError,
    ContractsUnavailableError,
    DeploymentMismatchError,
    LedgerError,
    RpcError,
)
from robocloud.ledger.models import (
    Advertised,
    Advertisement,
    Anchor,
    IndexedAdvertisement,
    RegisteredRobot,
    RegistrationMode,
    Robot,
    Role,
)
from robocloud.ledger.rpc import JsonRpcClient, as_revert
from robocloud.ledger.transactions import (
    FeeLimits,
    Receipt,
    SignedTransaction,
    Transactor,
    check_chain,
    quantity,
)


@dataclass(frozen=True)
class ContractAddresses:
    registry: str
    anchor_log: str

    @classmethod
    def from_service(cls, body: Any) -> ContractAddresses:
        """Parse ``GET /v1/contracts``: ``{"contracts": {"Registry": {"address": ...}, ...}}``."""
        contracts = body.get("contracts") if isinstance(body, dict) else None
        found = {
            name: entry.get("address")
            for name, entry in (contracts if isinstance(contracts, dict) else {}).items()
            if isinstance(entry, dict)
        }
        if not (found.get("Registry") and found.get("AnchorLog")):
            raise ContractsUnavailableError(
                f"the ledger's /v1/contracts lacks Registry or AnchorLog addresses: "
                f"{repr(body)[:200]}"
            )
        try:
            return cls(checksum(found["Registry"]), checksum(found["AnchorLog"]))
        except AddressError as exc:
            raise ContractsUnavailableError(f"the ledger's /v1/contracts: {exc}") from exc


def checksum(address: object) -> str:
    """The checksummed form of an address; ``AddressError`` (a ``ValueError``) if it is not one."""
    if not isinstance(address, str) or not is_address(address):
        raise AddressError(f"not an Ethereum address: {repr(address)[:100]}")
    return str(to_checksum_address(address))


def _topic_address(address: str) -> str:
    return "0x" + "00" * 12 + checksum(address)[2:].lower()


def _topic_uint(value: int) -> str:
    return "0x" + value.to_bytes(32, "big").hex()


_Blocks = tuple[int, int | None]
"""An ``eth_getLogs`` filter's ``fromBlock`` and ``toBlock`` (None: the latest block)."""


class LedgerService(ServiceClient):
    """The ledger service's REST routes: where the contracts are, the faucet, indexed reads.

    What these answer comes from the service's event index: convenient and fast, but for a
    check that matters, read the chain through ``Ledger`` (``eth_call``) instead.
    """

    default_service = "ledger"

    def contracts(self) -> ContractAddresses:
        """``GET /v1/contracts``: where Registry and AnchorLog are deployed."""
        return ContractAddresses.from_service(self.get_json("/v1/contracts"))

    def faucet(self, address: str) -> Any:
        """``POST /v1/faucet`` (signed): fund ``address``, which must be the signer's own."""
        return self.post_json("/v1/faucet", {"address": checksum(address)})

    def robot(self, address: str) -> RegisteredRobot | None:
        """``GET /v1/robots/{address}``: the indexed record (registered or pending), or None."""
        try:
            body = self.get_json(f"/v1/robots/{checksum(address)}")
        except NotFoundError:
            return None
        record = _robot_record(body, f"the ledger's record of {address}")
        if record.address != checksum(address):
            raise InvalidAnswerError(
                f"asked for the record of {checksum(address)}, the ledger answered one of "
                f"{record.address[:64]!r}"
            )
        return record

    def pending(self, limit: int = 100) -> list[RegisteredRobot]:
        """``GET /v1/registrations``: robots awaiting a registrar, oldest first.

        An answer holding more than ``limit`` entries, or an entry that is not pending, is an
        ``InvalidAnswerError``: whoever approves from this list must see what it says it is.
        """
        body = self.get_json("/v1/registrations", params={"limit": limit})
        if not isinstance(body, dict) or not isinstance(body.get("pending"), list):
            raise InvalidAnswerError("the ledger's pending registrations are not a list")
        if len(body["pending"]) > limit:
            raise InvalidAnswerError(
                f"the ledger sent {len(body['pending'])} pending registrations, "
                f"more than the {limit} asked for"
            )
        records = [_robot_record(item, "a pending registration") for item in body["pending"]]
        for record in records:
            if not record.pending:
                raise InvalidAnswerError(
                    f"the ledger listed {record.address[:64]!r} as pending, "
                    f"with status {record.status!r}"
                )
        return records

    def advertisements(
        self,
        *,
        since: int = 0,
        limit: int = 100,
        cid: str | None = None,
        advertiser: str | None = None,
        after_log_index: int | None = None,
        wait_s: float = 0,
    ) -> list[IndexedAdvertisement]:
        """``GET /v1/advertisements``: Advertised events from block ``since`` on, oldest first;
        with ``after_log_index``, block ``since``'s only past that log index (the position of
        the last event read, so that a reader gets past a block with more than ``limit``).
        With ``wait_s`` (at most ``MAX_WAIT_S``), a long poll: when there are none yet, the
        ledger answers as soon as a block brings one, else with none after ``wait_s``.

        An answer with more than ``limit`` events, events out of order or not past the
        position asked for, or a malformed event is an ``InvalidAnswerError``: a follower
        that trusted it could skip advertisements for good.
        """
        if not 0 <= wait_s <= MAX_WAIT_S:
            raise ValueError(f"wait_s must be between 0 and {MAX_WAIT_S:g} s, not {wait_s}")
        params: dict[str, str | int | float] = {"since": since, "limit": limit}
        if wait_s:
            params["wait_s"] = wait_s
        if after_log_index is not None:
            params["after_log_index"] = after_log_index
        if cid is not None:
            params["cid"] = cid
        if advertiser is not None:
            params["advertiser"] = checksum(advertiser)
        body = self.get_json("/v1/advertisements", params=params)
        if not isinstance(body, dict) or not isinstance(body.get("advertisements"), list):
            raise InvalidAnswerError("the ledger's advertisements are not a list")
        items = body["advertisements"]
        if len(items) > limit:
            raise InvalidAnswerError(
                f"the ledger sent {len(items)} advertisements, more than the {limit} asked for"
            )
        events = [_advertisement(item) for item in items]
        order = [(event.block_number, event.log_index) for event in events]
        position = (since, -1 if after_log_index is None else after_log_index)
        if order != sorted(order) or any(place <= position for place in order):
            raise InvalidAnswerError("the ledger's advertisements are out of order")
        return events


def _check_filtered(
    contract: ContractAbi, raw: Any, log: DecodedLog, topics: list[str | None], blocks: _Blocks
) -> None:
    """A log ``eth_getLogs`` answered must be one the filter asked for: its indexed arguments
    those the filter names, its block within the filter's range. A storage node recovering
    after a crash took another node's anchor, of another epoch and an older block, for its
    own; the refusal names what differs, so an operator can tell a lying node from a bug."""
    sent = raw.get("topics") if isinstance(raw, dict) else None
    sent = [str(topic).lower() for topic in sent] if isinstance(sent, list) else []
    inputs = contract.events[log.event]["inputs"]
    names = ["event", *(str(param["name"]) for param in inputs if param["indexed"])]
    differing = [
        names[position] if position < len(names) else f"topic {position}"
        for position, wanted in enumerate(topics)
        if wanted is not None and (position >= len(sent) or sent[position] != wanted.lower())
    ]
    if differing:
        raise InvalidAnswerError(
            f"the node answered eth_getLogs with a {log.event} log whose "
            f"{', '.join(differing)} differ from the filter's (block {log.block_number}, "
            f"transaction {log.tx_hash[:80]})"
        )
    first, last = blocks
    if log.block_number < first or (last is not None and log.block_number > last):
        raise InvalidAnswerError(
            f"the node answered eth_getLogs with a {log.event} log of block {log.block_number}, "
            f"outside the filter's blocks {first} to {'latest' if last is None else last}"
        )


def _decoded(contract: ContractAbi, log: Any) -> DecodedLog | None:
    """``contract.decode_log`` of a log a node sent; a malformed one is an
    ``InvalidAnswerError`` (a node's word, not a bug here)."""
    try:
        return contract.decode_log(log)
    except (AttributeError, DecodingError, KeyError, TypeError, ValueError) as exc:
        raise InvalidAnswerError(
            f"the node sent a malformed log of {contract.name} ({type(exc).__name__}: "
            f"{str(exc)[:200]})"
        ) from exc


def _advertisement(item: Any) -> IndexedAdvertisement:
    try:
        description = item["description"]
        event = IndexedAdvertisement(
            cid=_optional_cid(item["cid"]),
            advertiser=checksum(item["advertiser"]),
            description=_optional_cid(description["cid"]) if description is not None else None,
            first=item["first"],
            timestamp=item["timestamp"],
            block_number=item["block_number"],
            log_index=item["log_index"],
            tx_hash=item["tx"],
        )
        for number in (event.timestamp, event.block_number, event.log_index):
            if isinstance(number, bool) or not isinstance(number, int) or number < 0:
                raise ValueError(f"{number!r} is not a block number, log index or time")
        if not isinstance(event.first, bool) or not isinstance(event.tx_hash, str):
            raise ValueError("first or tx is malformed")
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidAnswerError(f"an advertisement from the ledger is malformed: {exc}") from None
    return event


def _optional_cid(text: object) -> str | None:
    if text is None:
        return None
    if not isinstance(text, str):
        raise ValueError(f"{text!r} is not CID text")
    return str(parse_cid(text, "cid"))


def _robot_record(body: Any, what: str) -> RegisteredRobot:
    try:
        record = RegisteredRobot.from_service(body)
        checksum(record.address)
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidAnswerError(f"{what} is malformed: {exc}") from exc
    return record


class Ledger(Closeable):
    """robocloud's contracts on one chain, seen and driven by one (optional) identity.

    With a deployment (``deployment=``, else the JSON-RPC client's, which defaults to
    ``ROBOCLOUD_EXPECTED_DEPLOYMENT``) of the form ``<chain id>:<Registry>``, the Registry must be
    that one and the node's chain that chain, or nothing is signed
    (``DeploymentMismatchError``).
    """

    def __init__(
        self,
        rpc: JsonRpcClient,
        addresses: ContractAddresses,
        identity: Identity | None = None,
        *,
        service: LedgerService | None = None,
        receipt_timeout_s: float = 60.0,
        deployment: str | None = None,
        fee_limits: FeeLimits | None = None,
    ) -> None:
        self.rpc = rpc
        self.addresses = addresses
        self.identity = identity
        self.service = service
        expected = deployment_chain(deployment or rpc.deployment)
        self.expected_chain_id = expected[0] if expected is not None else None
        if expected is not None and addresses.registry.lower() != expected[1]:
            raise DeploymentMismatchError(
                f"the ledger says the Registry is {addresses.registry}, but the robot's "
                f"deployment's is {expected[1]} (ROBOCLOUD_EXPECTED_DEPLOYMENT)"
            )
        self.registry = ContractAbi.load("Registry")
        self.anchor_log = ContractAbi.load("AnchorLog")
        self._contracts = [self.registry, self.anchor_log]
        self._transactor = (
            Transactor(
                rpc,
                identity,
                contracts=self._contracts,
                receipt_timeout_s=receipt_timeout_s,
                chain_id=self.expected_chain_id,
                limits=fee_limits,
            )
            if identity is not None
            else None
        )

    @classmethod
    def connect(
        cls,
        ledger_url: str | None = None,
        identity: Identity | None = None,
        *,
        transport: httpx.BaseTransport | None = None,
        receipt_timeout_s: float = 60.0,
        deployment: str | None = None,
        fee_limits: FeeLimits | None = None,
    ) -> Ledger:
        """Through the ledger service: its ``/rpc``, its contract addresses and its faucet."""
        service = LedgerService(ledger_url, identity, transport=transport, deployment=deployment)
        rpc = JsonRpcClient(
            f"{service.base_url}/rpc", service="ledger", transport=transport, deployment=deployment
        )
        try:
            return cls(
                rpc,
                service.contracts(),
                identity,
                service=service,
                receipt_timeout_s=receipt_timeout_s,
                fee_limits=fee_limits,
            )
        except BaseException:
            rpc.close()
            service.close()
            raise

    def close(self) -> None:
        self.rpc.close()
        if self.service is not None:
            self.service.close()

    # ----- chain -----

    @property
    def chain_id(self) -> int:
        """The node's chain id, checked against the deployment's when there is one; with a
        key, the one its transactions are signed for, asked once: a storage node asked again
        after anchoring and published whatever a node answered then beside its anchor."""
        if self._transactor is not None:
            return self._transactor.chain_id
        return check_chain(quantity(self.rpc.request("eth_chainId", [])), self.expected_chain_id)

    def block_number(self) -> int:
        return quantity(self.rpc.request("eth_blockNumber", []))

    def balance(self, address: str | None = None) -> int:
        """Balance in wei of ``address`` (default: this identity)."""
        target = checksum(address or self._signer().address)
        return quantity(self.rpc.request("eth_getBalance", [target, "latest"]))

    def faucet(self, *, timeout_s: float = 30.0) -> Any:
        """Ask the development chain's faucet to fund this identity; wait until it is funded.

        The request is signed, so the faucet funds the key that asked and nobody else.
        """
        identity = self._signer()
        if self.service is None:
            raise LedgerError("the faucet needs the ledger service: use Ledger.connect(url)")
        answer = self.service.faucet(identity.address)
        deadline = time.monotonic() + timeout_s
        while self.balance() == 0:
            if time.monotonic() >= deadline:
                raise LedgerError(f"the faucet did not fund {identity.address} in {timeout_s:g} s")
            time.sleep(0.1)
        return answer

    # ----- Registry writes -----

    def register(self, metadata_cid: bytes) -> Receipt:
        """Register this identity as a robot described by ``metadata_cid`` (binary CID)."""
        return self._send(self.registry, self.addresses.registry, "register", metadata_cid)

    def update_metadata(self, metadata_cid: bytes) -> Receipt:
        return self._send(self.registry, self.addresses.registry, "updateMetadata", metadata_cid)

    def deactivate(self) -> Receipt:
        return self._send(self.registry, self.addresses.registry, "deactivate")

    def reactivate(self) -> Receipt:
        return self._send(self.registry, self.addresses.registry, "reactivate")

    def advertise(
        self,
        cid: bytes,
        description_cid: bytes = b"",
        *,
        before_send: Callable[[SignedTransaction], None] | None = None,
    ) -> Advertised:
        """Announce that this robot holds ``cid``; ``first`` says whether nobody had before.

        ``before_send`` gets the signed transaction before it is sent, for a caller to save
        it and, after a crash, learn what it advertised with ``advertised_by``.
        """
        receipt = self._send(
            self.registry,
            self.addresses.registry,
            "advertise",
            cid,
            description_cid,
            before_send=before_send,
        )
        return self._advertised_in(receipt, cid, {"descriptionCid": description_cid})

    def advertised_by(
        self,
        signed: SignedTransaction,
        cid: bytes,
        *,
        before_send: Callable[[SignedTransaction], None] | None = None,
    ) -> Advertised | None:
        """The advertisement of ``cid`` made by ``signed``, an advertise transaction saved
        before a crash cut its sending or its wait short: sent again while the node lacks it
        and waited for (``Transactor.resume``), rather than another advertisement signed;
        replaced at a higher price, given to ``before_send`` first, once it has waited past
        the receipt timeout. None when it reverted, or its nonce went to another transaction
        (it never will be mined)."""
        transactor = self._signing(self.registry, "advertise")
        receipt = transactor.resume(signed, before_send=before_send)
        if receipt is None or receipt.status == 0:
            return None
        return self._advertised_in(receipt, cid, {})

    def _advertised_in(self, receipt: Receipt, cid: bytes, expected: dict[str, Any]) -> Advertised:
        """The receipt's ``Advertised`` event: of ``cid`` by this robot, and ``expected``."""
        expected = {
            "cidHash": keccak(cid),
            "advertiser": self._signer().address,
            "cid": cid,
            **expected,
        }
        return self._advertised(
            self._one_log(receipt, self.registry, self.addresses.registry, "Advertised", expected)
        )

    def grant_role(self, account: str, role: Role) -> Receipt:
        """Admin only."""
        return self._send(
            self.registry, self.addresses.registry, "grantRole", checksum(account), role.id
        )

    def revoke_role(self, account: str, role: Role) -> Receipt:
        """Admin only."""
        return self._send(
            self.registry, self.addresses.registry, "revokeRole", checksum(account), role.id
        )

    def set_suspended(self, account: str, suspended: bool) -> Receipt:
        """Admin only."""
        return self._send(
            self.registry, self.addresses.registry, "setSuspended", checksum(account), suspended
        )

    def approve(self, account: str) -> Receipt:
        """Admit a pending registration (the admin, or an active robot with the registrar role)."""
        return self._send(self.registry, self.addresses.registry, "approve", checksum(account))

    def reject(self, account: str) -> Receipt:
        """Refuse a pending registration (the admin or a registrar); the robot may ask again."""
        return self._send(self.registry, self.addresses.registry, "reject", checksum(account))

    def set_registration_mode(self, mode: RegistrationMode) -> Receipt:
        """Admin only."""
        return self._send(self.registry, self.addresses.registry, "setRegistrationMode", mode.value)

    # ----- Registry reads -----

    def robot(self, address: str) -> Robot:
        target = checksum(address)
        metadata, registered_at, registered, active, suspended = self._call(
            self.registry, self.addresses.registry, "getRobot", target
        )
        return Robot(target, metadata, registered_at, registered, active, suspended)

    def is_pending(self, address: str) -> bool:
        """Whether ``address`` asked to register and awaits a registrar (Approved mode)."""
        return bool(
            self._call(self.registry, self.addresses.registry, "isPending", checksum(address))[0]
        )

    def registration_mode(self) -> RegistrationMode:
        mode = self._call(self.registry, self.addresses.registry, "registrationMode")[0]
        try:
            return RegistrationMode(int(mode))
        except ValueError:
            raise InvalidAnswerError(
                f"the Registry's registration mode {mode} is unknown"
            ) from None

    def is_active(self, address: str) -> bool:
        return bool(
            self._call(self.registry, self.addresses.registry, "isActive", checksum(address))[0]
        )

    def has_role(self, address: str, role: Role, *, active: bool = True) -> bool:
        """Whether ``address`` holds ``role`` (and, by default, is an active robot)."""
        function = "isActiveWithRole" if active else "hasRole"
        result = self._call(
            self.registry, self.addresses.registry, function, checksum(address), role.id
        )
        return bool(result[0])

    def admin(self) -> str:
        return str(self._call(self.registry, self.addresses.registry, "admin")[0])

    def advertisement(self, cid: bytes) -> Advertisement | None:
        """The first advertiser and time of ``cid``, or None if nobody advertised it."""
        first, timestamp, block, count, description = self._call(
            self.registry, self.addresses.registry, "getAdvertisement", cid
        )
        if count == 0:
            return None
        return Advertisement(cid, first, timestamp, block, count, description)

    def advertisements(
        self, *, cid: bytes | None = None, advertiser: str | None = None, from_block: int = 0
    ) -> list[Advertised]:
        """Every ``Advertised`` event matching the filters, oldest first (``eth_getLogs``)."""
        topics: list[str | None] = [
            "0x" + self.registry.event_topic("Advertised").hex(),
            "0x" + keccak(cid).hex() if cid is not None else None,
            _topic_address(advertiser) if advertiser is not None else None,
        ]
        logs = self._logs(self.registry, self.addresses.registry, topics, (from_block, None))
        return [self._advertised(log) for log in logs]

    # ----- AnchorLog -----

    def anchor(
        self,
        epoch: int,
        root: bytes,
        record_count: int,
        *,
        before_send: Callable[[SignedTransaction], None] | None = None,
    ) -> Anchor:
        """Publish this storage node's TMT root for ``epoch`` (storage-node role needed).

        ``before_send`` gets the signed transaction before it is sent, for a caller to save
        it and, after a crash, learn what it anchored with ``anchored_by``.
        """
        receipt = self._send(
            self.anchor_log,
            self.addresses.anchor_log,
            "anchor",
            epoch,
            root,
            record_count,
            before_send=before_send,
        )
        return self._anchored_in(receipt, epoch, root, record_count)

    def anchored_by(
        self,
        signed: SignedTransaction,
        epoch: int,
        root: bytes,
        record_count: int,
        *,
        before_send: Callable[[SignedTransaction], None] | None = None,
    ) -> Anchor | None:
        """The anchor of ``epoch`` made by ``signed``, an anchor transaction saved before a
        crash cut its sending or its wait short: sent again while the node lacks it and waited
        for (``Transactor.resume``), rather than another anchor signed; replaced at a higher
        price, given to ``before_send`` first, once it has waited past the receipt timeout.
        None when it reverted, or its nonce went to another transaction (it never will be
        mined)."""
        transactor = self._signing(self.anchor_log, "anchor")
        receipt = transactor.resume(signed, before_send=before_send)
        if receipt is None or receipt.status == 0:
            return None
        return self._anchored_in(receipt, epoch, root, record_count)

    def _anchored_in(self, receipt: Receipt, epoch: int, root: bytes, record_count: int) -> Anchor:
        """The receipt's ``Anchored`` event: this node's, of ``epoch``, ``root`` and count."""
        expected = {
            "node": self._signer().address,
            "epoch": epoch,
            "root": root,
            "recordCount": record_count,
        }
        return self._anchored(
            self._one_log(receipt, self.anchor_log, self.addresses.anchor_log, "Anchored", expected)
        )

    def anchor_at(self, node: str, epoch: int) -> Anchor | None:
        """``node``'s anchor for ``epoch``, or None when it anchored nothing for it."""
        target = checksum(node)
        root, count, timestamp, block = self._call(
            self.anchor_log, self.addresses.anchor_log, "anchorAt", target, epoch
        )
        if timestamp == 0:
            return None
        try:
            check_block(block)
        except ValueError as exc:
            raise InvalidAnswerError(
                f"the node's answer to AnchorLog.anchorAt is not its result: {exc}"
            ) from None
        return Anchor(target, epoch, root, count, timestamp, block)

    def latest_anchor(self, node: str) -> Anchor | None:
        target = checksum(node)
        if self._call(self.anchor_log, self.addresses.anchor_log, "anchorCount", target)[0] == 0:
            return None
        epoch = self._call(self.anchor_log, self.addresses.anchor_log, "latest", target)[0]
        return self.anchor_at(target, epoch)

    def anchors(
        self,
        *,
        node: str | None = None,
        epoch: int | None = None,
        from_block: int = 0,
        to_block: int | None = None,
    ) -> list[Anchor]:
        """Every ``Anchored`` event matching the filters, oldest first (``eth_getLogs``), in
        blocks ``from_block`` to ``to_block`` (None: the latest)."""
        topics: list[str | None] = [
            "0x" + self.anchor_log.event_topic("Anchored").hex(),
            _topic_address(node) if node is not None else None,
            _topic_uint(epoch) if epoch is not None else None,
        ]
        blocks = (from_block, to_block)
        logs = self._logs(self.anchor_log, self.addresses.anchor_log, topics, blocks)
        return [self._anchored(log) for log in logs]

    # ----- internals -----

    def _signer(self) -> Identity:
        if self.identity is None:
            raise MissingIdentityError("this ledger operation needs the robot's identity")
        return self.identity

    def _send(
        self,
        contract: ContractAbi,
        address: str,
        function: str,
        *args: Any,
        before_send: Callable[[SignedTransaction], None] | None = None,
    ) -> Receipt:
        transactor = self._signing(contract, function)
        data = contract.encode_call(function, *args)
        return transactor.send(address, data, before_send=before_send)

    def _signing(self, contract: ContractAbi, function: str) -> Transactor:
        if self._transactor is None:
            raise MissingIdentityError(f"{contract.name}.{function} must be signed by a robot")
        return self._transactor

    def _call(
        self, contract: ContractAbi, address: str, function: str, *args: Any
    ) -> tuple[Any, ...]:
        call: dict[str, str] = {
            "to": address,
            "data": "0x" + contract.encode_call(function, *args).hex(),
        }
        try:
            result = self.rpc.request("eth_call", [call, "latest"])
        except RpcError as exc:
            raise as_revert(exc, self._contracts) or exc from exc
        try:
            if not isinstance(result, str) or not result.startswith("0x"):
                raise ValueError(f"{str(result)[:80]!r} is not 0x-hex")
            return contract.decode_output(function, bytes.fromhex(result[2:]))
        except (DecodingError, ValueError) as exc:
            raise InvalidAnswerError(
                f"the node's answer to {contract.name}.{function} is not its result: {exc}"
            ) from exc

    def _logs(
        self, contract: ContractAbi, address: str, topics: list[str | None], blocks: _Blocks
    ) -> list[DecodedLog]:
        while topics and topics[-1] is None:
            topics.pop()
        first, last = blocks
        query = {
            "address": address,
            "topics": topics,
            "fromBlock": hex(first),
            "toBlock": "latest" if last is None else hex(last),
        }
        raw_logs = self.rpc.request("eth_getLogs", [query])
        if not isinstance(raw_logs, list):
            raise InvalidAnswerError("the node's answer to eth_getLogs is not a list")
        found = []
        for raw in raw_logs:
            log = _decoded(contract, raw)
            if log is None or log.address != checksum(address):
                continue
            _check_filtered(contract, raw, log, topics, blocks)
            found.append(log)
        return found

    @staticmethod
    def _one_log(
        receipt: Receipt,
        contract: ContractAbi,
        address: str,
        event: str,
        expected: dict[str, Any],
    ) -> DecodedLog:
        """The transaction's ``event`` as emitted by the contract at ``address`` in the
        receipt's block, its arguments ``expected``: a log of the same shape from any other
        contract (one the transaction called, or one the node made up) says nothing about
        robocloud's, and arguments the node invents (another node, another epoch) would be
        returned as this transaction's."""
        for raw in receipt.logs:
            log = _decoded(contract, raw)
            if (
                log is not None
                and log.event == event
                and log.address == checksum(address)
                and log.tx_hash.lower() == receipt.tx_hash.lower()
            ):
                differing = [name for name, value in expected.items() if log.args[name] != value]
                if differing or log.block_number != receipt.block_number:
                    raise InvalidAnswerError(
                        f"the node's {event} event of transaction {receipt.tx_hash} is not the "
                        f"transaction's: its {', '.join(differing) or 'block'} differ"
                    )
                return log
        raise LedgerError(f"transaction {receipt.tx_hash} emitted no {event} event of {address}")

    @staticmethod
    def _advertised(log: DecodedLog) -> Advertised:
        args = log.args
        return Advertised(
            cid=args["cid"],
            advertiser=args["advertiser"],
            description_cid=args["descriptionCid"],
            first=args["first"],
            timestamp=args["timestamp"],
            block_number=log.block_number,
            tx_hash=log.tx_hash,
        )

    @staticmethod
    def _anchored(log: DecodedLog) -> Anchor:
        args = log.args
        return Anchor(
            node=args["node"],
            epoch=args["epoch"],
            root=args["root"],
            record_count=args["recordCount"],
            timestamp=args["timestamp"],
            block_number=log.block_number,
            tx_hash=log.tx_hash,
        )
