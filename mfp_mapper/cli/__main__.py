"""``python -m mfp_mapper.cli``: the ``mfp-mapper`` command line."""

from __future__ import annotations

import sys

if __name__ == "__main__":
    from mfp_mapper.cli.main import main

    sys.exit(main())
