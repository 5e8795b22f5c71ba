"""``mfp-mapper plot-convergence``: one cell probed repeatedly, DoO against classic occupancy
(Fig. 9)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mfp_mapper.cli.common import check_folder_writable, check_writable, nonneg_int


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """The ``plot-convergence`` subcommand's arguments."""
    p = sub.add_parser(
        "plot-convergence", help="one cell probed repeatedly: DoO vs classic occupancy (Fig. 9)"
    )
    p.add_argument("-o", "--output", required=True, help="PNG file or directory")
    p.add_argument("--returns", type=nonneg_int, default=10, help="reflected rays first")
    p.add_argument("--passes", type=nonneg_int, default=40, help="then rays passing through")
    return p


def run(args: argparse.Namespace) -> int:
    from mfp_mapper.outputs.render import plot_convergence

    out = Path(args.output)
    if out.is_dir():
        check_folder_writable(out)
    else:
        check_writable(out)
    print(f"wrote {plot_convergence(args.output, args.returns, args.passes)}")
    return 0
