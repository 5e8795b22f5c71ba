"""The ``mfp-mapper`` command line. ``main`` and ``build_parser`` live in ``cli.main`` and
``cli.args``; heavy modules are imported by each subcommand only when it runs."""

from __future__ import annotations

from mfp_mapper.cli.args import build_parser
from mfp_mapper.cli.main import main

__all__ = ["build_parser", "main"]
