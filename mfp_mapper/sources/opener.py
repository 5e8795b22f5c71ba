"""The one way to open a recording: ``open_recording`` takes a bag, a folder of scan files or
a simulation and gives a ``sources.recording.Recording``.

``poses`` and ``times`` are the ``--poses``/``--times`` flags: a scan folder needs poses (a
pose file, ``identity``, or ``opts.replay.odometry``); a bag has its own (odometry or /tf)
unless ``poses`` names a TUM file or an odometry CSV to match by stamp, or
``opts.replay.odometry`` asks for KISS-ICP; ``times`` is for scan folders only.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from mfp_mapper.config.replay_options import ReplayError, ReplayOptions
from mfp_mapper.sources.bags import open_bag
from mfp_mapper.sources.recording import Recording
from mfp_mapper.sources.scan_folder import is_scan_folder, open_folder
from mfp_mapper.sources.simulate import SimulationConfig, open_simulation


def open_recording(
    source: str | Path | SimulationConfig,
    opts: ReplayOptions | None = None,
    poses: str | Path | None = None,
    times: str | Path | None = None,
    log: Callable[[str], None] | None = None,
) -> Recording:
    """``source`` opened as a recording: a bag (ROS 1 ``.bag``, a ROS 2 bag directory or
    its ``.db3``/``.mcap`` file), a folder of scan files, or a ``SimulationConfig``.
    ReplayError says why it cannot be used (before any cloud is mapped)."""
    opts = opts or ReplayOptions()
    if poses is not None and opts.replay.odometry is not None:
        raise ReplayError("give either --poses or --odometry, not both")
    if isinstance(source, SimulationConfig):
        if poses is not None or times is not None:
            raise ReplayError("a simulation has its true poses: no --poses or --times")
        return open_simulation(source, opts)
    if is_scan_folder(source):
        return open_folder(source, opts, poses, times, log)
    if times is not None:
        raise ReplayError(f"{source}: --times is for folders of scan files")
    return open_bag(source, opts, poses, log)


@contextmanager
def opened(
    source: Recording | str | Path,
    opts: ReplayOptions | None = None,
    log: Callable[[str], None] | None = None,
) -> Iterator[Recording]:
    """``source`` itself when it is a recording (left open: its opener closes it), else
    ``open_recording(source, opts)``, closed on leaving."""
    if isinstance(source, Recording):
        yield source
        return
    with open_recording(source, opts, log=log) as recording:
        yield recording
