"""``python -m mfp_mapper.node``: the ROS 2 node (implemented in ``mfp_mapper.ros.node``)."""

from __future__ import annotations

import sys

if __name__ == "__main__":
    from mfp_mapper.ros.node import main

    sys.exit(main())
