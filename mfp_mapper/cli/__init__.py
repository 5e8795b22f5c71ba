"""The ``mfp-mapper`` command line: ``main`` and ``build_parser`` (``cli.main``), one module
per subcommand; heavy modules are imported by a subcommand only when it runs."""

from __future__ import annotations

from mfp_mapper.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
