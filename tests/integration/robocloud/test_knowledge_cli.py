"""A robot describes its files and asks the knowledge base, through the CLI, against a real
ledger, cas and storage node."""

from __future__ import annotations

import csv
import io
import json
import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from robocloud import semantic
from robocloud.cas import Cas
from robocloud.cid import CID
from robocloud.cli import app
from robocloud.identity import Identity
from robocloud.knowledge import Knowledge
from robocloud.ledger import Ledger
from robocloud.unixfs import import_bytes
from tests.procs import ServiceProcess

runner = CliRunner()
METADATA = bytes.fromhex("01551220") + bytes(range(32))


def jpeg(width: int, height: int, salt: bytes) -> bytes:
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, height, width, 3) + b"\x00" * 9
    return b"\xff\xd8" + sof + salt + b"\xff\xd9"


class Robot:
    def __init__(
        self,
        ledger: ServiceProcess,
        cas: ServiceProcess,
        storage: ServiceProcess,
        keystore: Path,
        identity: Identity,
    ) -> None:
        self.ledger, self.cas, self.storage = ledger, cas, storage
        self.keystore = keystore
        self.identity = identity

    def cli(self, *args: str) -> tuple[int, str]:
        urls = ["--cas", self.cas.url, "--storage", self.storage.url, "--ledger", self.ledger.url]
        done = runner.invoke(
            app, [*args, "-k", str(self.keystore), *urls], env={"ROBOCLOUD_PASSPHRASE": "pw"}
        )
        return done.exit_code, done.output

    def sparql(self, query: str, *options: str) -> tuple[int, str]:
        done = runner.invoke(app, ["sparql", query, "--storage", self.storage.url, *options])
        return done.exit_code, done.output


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    root = tmp_path_factory.mktemp("knowledge-cli")
    identity = Identity.generate()
    keystore = root / "key.json"
    identity.save(keystore, "pw", scrypt_n=2**4)
    with (
        ServiceProcess("ledger", root / "ledger") as ledger,
        ServiceProcess("cas", root / "cas") as cas,
        ServiceProcess(
            "storage",
            root / "storage",
            {
                "ROBOCLOUD_CAS_URL": cas.url,
                "ROBOCLOUD_LEDGER_URL": ledger.url,
                "ROBOCLOUD_STORAGE_ANCHOR": "false",
                "ROBOCLOUD_STORAGE_REGISTER": "false",
                "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
            },
        ) as storage,
    ):
        with Ledger.connect(ledger.url, identity, receipt_timeout_s=30) as chain:
            chain.faucet()
            chain.register(METADATA)
        yield Robot(ledger, cas, storage, keystore, identity)


def test_describe_stores_indexes_and_advertises_each_file(robot: Robot, tmp_path: Path) -> None:
    first, second = tmp_path / "a.jpg", tmp_path / "b.jpg"
    first.write_bytes(jpeg(640, 480, b"a"))
    second.write_bytes(jpeg(320, 240, b"b"))
    code, output = robot.cli(
        "describe", str(first), str(second), "--sensor", "camera_front", "--advertise", "--json"
    )
    assert code == 0, output
    results = json.loads(output)
    assert [r["cid"] for r in results] == [
        str(import_bytes(first.read_bytes())[1]),
        str(import_bytes(second.read_bytes())[1]),
    ]
    robot_did = robot.identity.did(1337)
    with Cas(robot.cas.url) as cas, Ledger.connect(robot.ledger.url) as chain:
        for result in results:
            assert cas.get(result["cid"]) in (first.read_bytes(), second.read_bytes())
            description = semantic.parse_canonical(cas.get(result["description"]))
            assert str(description.cid()) == result["description"]
            assert description.subjects() == {f"ipfs://{result['cid']}": "file"}
            assert f"<{robot_did}>".encode() in description.canonical()
            advertisement = chain.advertisement(CID.decode(result["cid"]).binary)
            assert advertisement is not None
            assert advertisement.description_cid == CID.decode(result["description"]).binary

    code, output = robot.sparql(
        "PREFIX rc: <https://w3id.org/robocloud#> SELECT ?file ?width WHERE "
        f"{{ ?file rc:producedBy <{robot_did}> ; rc:width ?width }} ORDER BY ?width"
    )
    assert code == 0, output
    assert output.splitlines() == [
        "file\twidth",
        f"ipfs://{results[1]['cid']}\t320",
        f"ipfs://{results[0]['cid']}\t640",
    ]


def test_sparql_prints_each_format_and_a_refusal(robot: Robot, tmp_path: Path) -> None:
    image = tmp_path / "c.jpg"
    image.write_bytes(jpeg(100, 50, b"c"))
    assert robot.cli("describe", str(image))[0] == 0
    query = (
        "PREFIX rc: <https://w3id.org/robocloud#> SELECT ?w WHERE { ?f rc:width ?w ; rc:height 50 }"
    )
    code, output = robot.sparql(query, "--format", "csv")
    assert code == 0, output
    assert list(csv.reader(io.StringIO(output))) == [["w"], ["100"]]
    code, output = robot.sparql(query, "--json")
    assert json.loads(output)["results"]["bindings"] == [
        {
            "w": {
                "type": "literal",
                "value": "100",
                "datatype": "http://www.w3.org/2001/XMLSchema#integer",
            }
        }
    ]
    ask = "PREFIX rc: <https://w3id.org/robocloud#> ASK { ?f rc:height 50 }"
    assert robot.sparql(ask) == (0, "yes\n")
    query_file = tmp_path / "q.rq"
    query_file.write_text(
        "PREFIX rc: <https://w3id.org/robocloud#> "
        "CONSTRUCT { ?f rc:width ?w } WHERE { ?f rc:width ?w ; rc:height 50 }"
    )
    code, output = robot.sparql(f"@{query_file}", "--format", "turtle")
    assert code == 0, output
    assert "rc:width 100" in output

    code, output = robot.sparql(
        "PREFIX rc: <https://w3id.org/robocloud#> INSERT DATA { <urn:x> rc:width 1 }"
    )
    assert code == 4, output
    assert "updates are rejected" in output
    assert robot.sparql(query, "--format", "yaml")[0] == 2
    with Knowledge(robot.storage.url) as knowledge:
        assert knowledge.select(query) == [{"w": "100"}]
