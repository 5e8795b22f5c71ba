"""Large clouds over DDS: the Fast DDS large-data profile and what the node says about losses.

Plain Python (no rclpy): the launch file builds the node's environment with
``node_environment``; the node words its first transport loss with ``transport_loss_text``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

PROFILE_FILE = "fastdds_large_data.xml"
"""config/fastdds_large_data.xml: shared memory 32 MiB segments, UDP 4 MiB buffers."""
PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
"""The variable Fast DDS 2.x (ROS 2 Jazzy's rmw_fastrtps_cpp) reads its XML profile from."""
FASTDDS_RMWS = ("", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp")
"""RMW_IMPLEMENTATION values that use Fast DDS ("" = Jazzy's default)."""


def profile_path() -> str:
    """Where config/fastdds_large_data.xml is: the installed share directory, else this
    checkout's config/ (a source tree or the venv)."""
    try:
        from ament_index_python.packages import (
            PackageNotFoundError,
            get_package_share_directory,
        )

        try:
            installed = Path(get_package_share_directory("mfp_mapper")) / "config" / PROFILE_FILE
            if installed.is_file():
                return str(installed)
        except (PackageNotFoundError, ValueError, LookupError, OSError):  # not installed
            pass
    except ImportError:
        pass
    return str(Path(__file__).resolve().parents[2] / "config" / PROFILE_FILE)


def node_environment(
    environ: Mapping[str, str], profile: str, enabled: bool
) -> tuple[dict[str, str], str]:
    """The variables to add to the mapper's environment, and one line saying why.

    ``enabled`` (launch argument ``large_data_profile``): set ``FASTRTPS_DEFAULT_PROFILES_FILE``
    to ``profile``, unless the environment already names a profile (the user's own wins) or
    another middleware than Fast DDS is selected (the file would mean nothing to it).
    """
    if not enabled:
        return {}, "large-data profile off (large_data_profile:=false): Fast DDS defaults"
    rmw = environ.get("RMW_IMPLEMENTATION", "")
    if rmw not in FASTDDS_RMWS:
        return {}, f"large-data profile not set: RMW_IMPLEMENTATION={rmw} is not Fast DDS"
    own = environ.get(PROFILE_ENV, "")
    if own:
        return {}, f"large-data profile not set: {PROFILE_ENV} already names {own}"
    return {PROFILE_ENV: profile}, f"{PROFILE_ENV}={profile} for the mapper"


def transport_loss_text(lost: int, queue: tuple[int, int]) -> str:
    """The one line the node logs at its first transport loss: what was lost, that it is not
    the node's backlog, and what to set (``queue``: clouds queued, ``cloud_queue_size``)."""
    here = os.environ.get(PROFILE_ENV, "")
    mine = (
        f"this process has {PROFILE_ENV}={here}" if here else f"this process has no {PROFILE_ENV}"
    )
    return (
        f"{lost} cloud(s) lost in transport before reaching this node (counted as "
        f"clouds_lost_transport in ~/status; the node's own backlog is counted apart, as "
        f"queue_full drops: {queue[0]} of {queue[1]} queued now). Large clouds need Fast DDS's "
        f"large-data profile in the publisher's (lidar driver's) process and in this one: "
        f"export {PROFILE_ENV}={profile_path()} ({mine}; the launch file sets it for the "
        "mapper; docs/robot.md, 'The DDS profile for large clouds')"
    )
