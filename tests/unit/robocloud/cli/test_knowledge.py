"""``robocloud describe --print``: the description built here from a file, and what is refused
before anything is sent; the image header reader on real and hostile headers."""

from __future__ import annotations

import struct
from datetime import datetime
from pathlib import Path

import pytest
from typer.testing import CliRunner

from robocloud import semantic
from robocloud.cli import app
from robocloud.cli.knowledge import image_size
from robocloud.identity import Identity
from robocloud.unixfs import import_bytes
from tests.procs import SHARED_DATA

runner = CliRunner()


def png(width: int, height: int) -> bytes:
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + header + b"\x00" * 4


def jpeg(width: int, height: int) -> bytes:
    app0 = (
        b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\x00" + b"\x01\x01\x00\x00\x01\x00\x01\x00\x00"
    )
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, height, width, 3) + b"\x00" * 9
    return b"\xff\xd8" + app0 + b"\xff\xff" + sof + b"\xff\xd9"


@pytest.mark.parametrize(
    ("header", "size"),
    [
        (png(640, 480), (640, 480)),
        (jpeg(1280, 720), (1280, 720)),
        (png(0, 480), None),
        (jpeg(0, 0), None),
        (b"\xff\xd8\xff\xe0\x00\x01", None),
        (b"\xff\xd8" + b"\xff\xe0\x00\x00" * 10, None),
        (b"\xff\xd8\x00\x00\x00\x00\x00\x00\x00\x00", None),
        (b"GIF89a", None),
        (jpeg(1280, 720)[:20], None),
        (b"", None),
    ],
)
def test_image_size_reads_png_and_jpeg_headers_and_nothing_else(
    header: bytes, size: tuple[int, int] | None
) -> None:
    assert image_size(header) == size


def test_describe_print_builds_a_valid_description_of_the_file(
    tmp_path: Path, keystore: Path, identity: Identity
) -> None:
    path = keystore
    image = tmp_path / "front.png"
    image.write_bytes(png(640, 480))
    done = runner.invoke(
        app,
        [
            "describe",
            str(image),
            "--chain-id",
            "1337",
            "-k",
            str(path),
            "--print",
            "ntriples",
            "--sensor",
            "camera_front",
            "--start",
            "2026-03-01T10:00:00+00:00",
            "--end",
            "2026-03-01T10:00:01+00:00",
        ],
    )
    assert done.exit_code == 0, done.output
    description = semantic.parse_canonical(done.stdout_bytes)
    semantic.validate(description)
    robot = identity.did(1337)
    assert (
        description.canonical()
        == semantic.file_description(
            import_bytes(png(640, 480))[1],
            "image/png",
            len(png(640, 480)),
            title="front.png",
            producer=robot,
            sensors=[semantic.sensor_iri(robot, "camera_front")],
            start=datetime.fromisoformat("2026-03-01T10:00:00+00:00"),
            end=datetime.fromisoformat("2026-03-01T10:00:01+00:00"),
            attributes={"width": 640, "height": 480},
        ).canonical()
    )


@pytest.mark.parametrize(
    ("recording", "media_type"),
    [
        ("mcap/rosbag2_cpp_only_topics.mcap", "application/vnd.mcap"),
        ("rosbag1/evo_tf_example.bag", "application/x-rosbag"),
        ("rosbag2/evo_tf_example/tf_example.db3", "application/vnd.sqlite3"),
    ],
)
def test_describe_knows_the_media_type_of_a_recording(
    keystore: Path, recording: str, media_type: str
) -> None:
    """A ROS bag, the data robots share most, was refused: "cannot tell the media type"."""
    path = SHARED_DATA / recording
    done = runner.invoke(
        app,
        ["describe", str(path), "--chain-id", "1337", "-k", str(keystore), "--print", "ntriples"],
    )
    assert done.exit_code == 0, done.output
    description = semantic.parse_canonical(done.stdout_bytes)
    semantic.validate(description)
    media = "<http://www.w3.org/ns/dcat#mediaType>"
    [line] = [line for line in done.stdout.splitlines() if media in line]
    assert f"<https://www.iana.org/assignments/media-types/{media_type}>" in line


@pytest.mark.parametrize(
    ("name", "options", "message"),
    [
        ("data.unknownext", [], "cannot tell the media type of data.unknownext"),
        ("a.png", ["--start", "yesterday"], "is not an ISO 8601 time"),
        ("a.png", ["--start", "2026-03-01T10:00:00"], "give the time zone"),
        ("a.png", ["--width", "-3"], "width -3 is not an integer of at least 1"),
        ("a.png", ["--sensor", "Front Cam"], "sensor name 'Front Cam'"),
        ("a.png", ["--media-type", "png"], "'png' is not a media type"),
        ("a.png", ["--print", "yaml"], "turtle, rdfxml or ntriples"),
        (
            "a.png",
            ["--start", "2026-03-02T00:00:00Z", "--end", "2026-03-01T00:00:00Z"],
            "is after end",
        ),
    ],
)
def test_describe_refuses_what_would_not_be_a_valid_description(
    tmp_path: Path, keystore: Path, identity: Identity, name: str, options: list[str], message: str
) -> None:
    path = keystore
    target = tmp_path / name
    target.write_bytes(png(2, 2))
    done = runner.invoke(
        app,
        [
            "describe",
            str(target),
            "--chain-id",
            "1337",
            "-k",
            str(path),
            "--print",
            "turtle",
            *options,
        ],
    )
    assert done.exit_code == 2, done.output
    assert message in done.output.replace("\n", " ")
    assert "@prefix" not in done.output
