"""The ``robocloud`` command line: what a robot's operator types."""

from robocloud.cli.main import app

__all__ = ["app"]
