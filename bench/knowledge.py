"""Knowledge base: application discovery over 1,000 applications and 10,000 files, and the store.

1. Discovery through the service: p50 of ``GET /v1/knowledge/applications?consumes=TYPE``
   (the issue asks for at most 50 ms) against the same SPARQL query on a plain rdflib Graph in
   this process (its ratio printed).
2. The store behind the knowledge base: rdflib's in-memory store against pyoxigraph through
   oxrdflib, on this workload (loading the graph, the discovery query, a large aggregate over
   every file) and on SHACL validation of descriptions (pyshacl over a data graph in each
   store). Both are printed; docs/semantics.md says which the service uses and why.
3. A worker's load of the description files: Oxigraph parsing each file itself (what the
   workers do) against reading each into rdflib terms first and adding those (what they did),
   on the same files, with its ratio.

    python bench/knowledge.py [--apps 1000] [--files 10000] [--queries 200]
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "clients")]

from rdflib import Graph, URIRef  # noqa: E402
from rdflib.plugins.sparql import prepareQuery  # noqa: E402

from robocloud import semantic  # noqa: E402
from robocloud.cid import CID  # noqa: E402
from robocloud.semantic import Description, Port  # noqa: E402
from services.common.durable import atomic_write  # noqa: E402
from services.storage.sparql import APPLICATIONS_QUERY  # noqa: E402
from tests.procs import ServiceProcess  # noqa: E402

MEDIA_TYPES = [
    "image/jpeg",
    "image/png",
    "image/tiff",
    "video/mp4",
    "audio/wav",
    "application/json",
    "application/x-ros-bag",
    "application/vnd.apache.parquet",
    "text/csv",
    "model/gltf-binary",
]
ROBOT = semantic.robot_iri(1337, "0x1a642f0E3c3aF545E7AcBD38b07251B3990914F1")
T0 = datetime(2026, 3, 1, tzinfo=UTC)
LARGE_QUERY = """PREFIX rc: <https://w3id.org/robocloud#>
PREFIX dcat: <http://www.w3.org/ns/dcat#>
SELECT ?type (COUNT(?file) AS ?files) (SUM(?size) AS ?bytes) (AVG(?width) AS ?width)
WHERE { ?file a rc:File ; dcat:mediaType ?type ; dcat:byteSize ?size ; rc:width ?width }
GROUP BY ?type ORDER BY ?type"""


def cid_of(kind: str, n: int) -> CID:
    return CID.from_block(f"{kind}-{n}".encode())


def applications(count: int, rng: random.Random) -> list[Description]:
    built = []
    for n in range(count):
        inputs = [
            Port(f"in{i}", media_type=rng.choice(MEDIA_TYPES), attributes=["width", "height"])
            for i in range(rng.randint(1, 2))
        ]
        outputs = [Port("out", media_type=rng.choice(MEDIA_TYPES), attributes=["width"])]
        built.append(
            semantic.application_description(
                cid_of("app", n), f"app_{n}", "1.0.0", inputs=inputs, outputs=outputs
            )
        )
    return built


def files(count: int, rng: random.Random) -> list[Description]:
    return [
        semantic.file_description(
            cid_of("file", n),
            rng.choice(MEDIA_TYPES),
            rng.randint(1, 10**7),
            producer=ROBOT,
            start=T0 + timedelta(seconds=n),
            end=T0 + timedelta(seconds=n + 1),
            attributes={"width": rng.choice([320, 640, 1280]), "height": 480},
        )
        for n in range(count)
    ]


def p50_ms(run: Callable[[], Any], times: int) -> float:
    samples = []
    for _ in range(times):
        start = time.perf_counter()
        run()
        samples.append((time.perf_counter() - start) * 1000)
    return statistics.median(samples)


def load(store: str, descriptions: list[Description]) -> tuple[Graph, float]:
    graph = Graph(store="Oxigraph") if store == "oxigraph" else Graph()
    start = time.perf_counter()
    if store == "oxigraph":
        graph.addN((s, p, o, graph) for d in descriptions for s, p, o in d.graph)
    else:
        for description in descriptions:
            for triple in description.graph:
                graph.add(triple)
    return graph, time.perf_counter() - start


def discovery(graph: Graph, store: str, wanted: list[str]) -> Callable[[], Any]:
    """The service's discovery query: prepared with bindings (rdflib) or as text (oxigraph)."""
    prepared = prepareQuery(APPLICATIONS_QUERY)
    position = [0]

    def run() -> int:
        iri = semantic.media_type_iri(wanted[position[0] % len(wanted)])
        position[0] += 1
        if store == "oxigraph":
            text = APPLICATIONS_QUERY.replace(
                "WHERE {", f"WHERE {{ VALUES ?consumes {{ <{iri}> }}", 1
            )
            return len(list(graph.query(text)))
        return len(list(graph.query(prepared, initBindings={"consumes": URIRef(iri)})))

    return run


def shacl(store: str, descriptions: list[Description]) -> Callable[[], Any]:
    from pyshacl import validate

    shapes = semantic.shapes()
    position = [0]

    def run() -> bool:
        description = descriptions[position[0] % len(descriptions)]
        position[0] += 1
        data = Graph(store="Oxigraph") if store == "oxigraph" else Graph()
        for triple in description.graph:
            data.add(triple)
        conforms = validate(data, shacl_graph=shapes)[0]
        assert conforms
        return bool(conforms)

    return run


def load_files_natively(paths: list[Path]) -> float:
    """Seconds to load the files as the workers do: Oxigraph's own N-Triples parser."""
    graph = Graph(store="Oxigraph")
    start = time.perf_counter()
    for path in paths:
        graph.parse(data=path.read_bytes(), format="ox-nt")
    return time.perf_counter() - start


def load_files_as_terms(paths: list[Path]) -> float:
    """Seconds to load the files as the workers did: each read into rdflib terms (the SDK's
    canonical reader), then added to Oxigraph 10,000 triples at a time."""
    graph = Graph(store="Oxigraph")
    start = time.perf_counter()
    quads: list[Any] = []
    for path in paths:
        description = semantic.parse_canonical(path.read_bytes())
        quads.extend((s, p, o, graph) for s, p, o in description.graph)
        if len(quads) >= 10_000:
            graph.addN(quads)
            quads.clear()
    graph.addN(quads)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--apps", type=int, default=1000)
    parser.add_argument("--files", type=int, default=10000)
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument(
        "--slow-queries",
        type=int,
        default=5,
        help="samples of rdflib's in-memory store on the discovery query (seconds each)",
    )
    args = parser.parse_args()
    rng = random.Random(16)

    start = time.perf_counter()
    apps, data = applications(args.apps, rng), files(args.files, rng)
    everything = apps + data
    print(
        f"built {len(apps)} application and {len(data)} file descriptions "
        f"({sum(len(d) for d in everything)} triples) in {time.perf_counter() - start:.1f} s"
    )

    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp) / "storage" / "knowledge" / "descriptions"
        for description in everything:
            atomic_write(directory / f"{description.cid()}.nt", description.canonical())
        start = time.perf_counter()
        storage = ServiceProcess(
            "storage",
            Path(tmp) / "storage",
            {
                "ROBOCLOUD_STORAGE_ANCHOR": "false",
                "ROBOCLOUD_KNOWLEDGE_FOLLOW_LEDGER": "false",
                "ROBOCLOUD_KNOWLEDGE_WORKERS": "1",
            },
        )
        try:
            storage.start(timeout_s=600)
            print(
                f"service ready with {len(everything)} descriptions in "
                f"{time.perf_counter() - start:.1f} s (workers load and warm the parser)"
            )
            url = f"{storage.url}/v1/knowledge/applications"
            position = [0]
            with httpx.Client(timeout=60) as client:

                def ask() -> int:
                    wanted = MEDIA_TYPES[position[0] % len(MEDIA_TYPES)]
                    position[0] += 1
                    answer = client.get(url, params={"consumes": wanted, "limit": 1000})
                    answer.raise_for_status()
                    return len(answer.json()["applications"])

                found = ask()
                service_p50 = p50_ms(ask, args.queries)
        finally:
            storage.stop()
        paths = sorted(directory.glob("*.nt"))
        native_s, terms_s = load_files_natively(paths), load_files_as_terms(paths)

    baseline, _ = load("memory", everything)
    baseline_p50 = p50_ms(discovery(baseline, "memory", MEDIA_TYPES), args.slow_queries)
    print(f"\n1. discovery: ~{found} applications per type among {len(apps)}")
    print(f"   service GET /v1/knowledge/applications p50 {service_p50:.1f} ms (target <= 50 ms)")
    print(f"   same SPARQL on a plain rdflib Graph     p50 {baseline_p50:.1f} ms")
    print(
        f"   ratio service / plain graph: {service_p50 / baseline_p50:.4f}x "
        f"(the plain graph is {baseline_p50 / service_p50:.0f}x slower)"
    )

    print("\n2. store: rdflib memory vs pyoxigraph (oxrdflib)")
    rows = []
    for store in ("memory", "oxigraph"):
        graph, load_s = load(store, everything)
        rows.append(
            (
                store,
                load_s,
                p50_ms(
                    discovery(graph, store, MEDIA_TYPES),
                    args.queries if store == "oxigraph" else args.slow_queries,
                ),
                p50_ms(
                    lambda graph=graph: list(graph.query(LARGE_QUERY)), max(args.queries // 20, 5)
                ),
                p50_ms(shacl(store, everything[:: max(len(everything) // 200, 1)]), args.queries),
            )
        )
    print(f"   {'store':<10}{'load s':>10}{'discovery ms':>15}{'aggregate ms':>15}{'SHACL ms':>12}")
    for store, load_s, disc, large, shapes in rows:
        print(f"   {store:<10}{load_s:>10.2f}{disc:>15.1f}{large:>15.1f}{shapes:>12.1f}")
    memory, oxigraph = rows
    print(
        f"   oxigraph / memory: load {oxigraph[1] / memory[1]:.2f}x, discovery "
        f"{oxigraph[2] / memory[2]:.2f}x, aggregate {oxigraph[3] / memory[3]:.2f}x, "
        f"SHACL {oxigraph[4] / memory[4]:.2f}x"
    )

    print(f"\n3. a worker's load of {len(paths)} description files")
    print(f"   Oxigraph's own parser      {native_s:.2f} s")
    print(f"   rdflib terms, then added   {terms_s:.2f} s")
    print(f"   ratio: {native_s / terms_s:.2f}x")


if __name__ == "__main__":
    main()
