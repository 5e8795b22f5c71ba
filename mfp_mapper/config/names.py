"""Names the CLI offers as choices, and the package version, kept apart so that
``mfp-mapper --help`` imports no numpy."""

VERSION = "0.2.0"
"""The package version (also in package.xml and setup.py; a test keeps them equal)."""

BAG_FORMATS = ("mcap", "sqlite3", "ros1")
"""Bag storages the simulator writes (ROS 2 mcap, ROS 2 sqlite3, ROS 1 .bag)."""

SCENES = ("demo", "small", "open")
"""The simulator's scene presets (``simulate.preset``)."""
