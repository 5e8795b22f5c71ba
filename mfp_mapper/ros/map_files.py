"""The node's map file: what it loads at configure, where and when it saves.

``map_path`` is loaded at configure (``initial_mapper``): a map file, or a tiled map when it
is a directory; temporary files of an interrupted save are removed first. A map that fails
to load is never saved over: the node starts an empty map and saves beside it
(``recovery_path``). Saves come from ``~/save_map``, the autosave timer (``autosave_period``,
only a map that changed; an empty ``map_path`` says so once at configure; a failing autosave
logs throttled) and cleanup or shutdown (``save_on_shutdown``), one at a time.

A file is overwritten only by the node that owns its contents: when ``map_path`` was changed
on disk since the node loaded or last wrote it (another process, an operator copying a new
map in), a map the node did not change since is not written at all (a frozen map in
localization mode), and a changed one is saved beside it (``recovery_path``) with a warning
saying why, never over it.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rclpy.callback_groups import CallbackGroup
from rclpy.clock import Clock
from std_srvs.srv import Trigger

from mfp_mapper.config.schema import NodeConfig
from mfp_mapper.core.mapper import Mapper, mapper_kwargs
from mfp_mapper.mapio.atomic import remove_stale_temp_files
from mfp_mapper.mapio.loading import load_map
from mfp_mapper.mapio.mapfile import MapFileError, map_blocks
from mfp_mapper.mapio.tiles import INDEX_NAME, is_tiled, write_map_path
from mfp_mapper.mapping.live import LiveIntegrator
from mfp_mapper.ros.guarded_node import GuardedNode, tracked_role


def initial_mapper(cfg: NodeConfig, logger: Any) -> tuple[Mapper, str | None]:
    """The map to start from: ``map_path`` when it exists and loads, else an empty one; and,
    when loading failed, the path saves go to instead (``recovery_path``): that file is
    never saved over."""
    path = cfg.node.map_path
    if path:  # temporary files of a save that was killed midway
        target = os.path.realpath(path)
        stale = remove_stale_temp_files(os.path.dirname(target), os.path.basename(target))
        if os.path.isdir(target):  # a tiled map: its index and tiles
            stale += remove_stale_temp_files(target) + remove_stale_temp_files(
                os.path.join(target, "tiles")
            )
        for name in stale:
            logger.info(f"removed {name}, left by an interrupted save")
    if not (path and os.path.lexists(path)) or (
        os.path.isdir(path) and not is_tiled(path) and not os.listdir(path)
    ):  # nothing yet, or an empty directory for a tiled map
        return empty_map(cfg), None
    try:
        mapper = load_map(path, **mapper_kwargs(cfg.map, cfg.sensor_model))
    except Exception as err:  # a map file never takes the node down (MemoryError included)
        text = f"{type(err).__name__}: {err}"
        if isinstance(err, MapFileError):  # it names its file: once is enough
            text = err.problem if err.path == Path(path) else str(err)
        other = recovery_path(path)
        logger.error(
            f"cannot load map_path {path!r}: {text}; starting an empty map, saved to "
            f"{other!r}, never over that file"
        )
        return empty_map(cfg), other
    if mapper.resolution != cfg.map.resolution:
        logger.warning(
            f"map {path!r} has resolution {mapper.resolution} m, parameter "
            f"resolution is {cfg.map.resolution} m: keeping the map's"
        )
    if cfg.map.frame_id and mapper.frame_id and mapper.frame_id != cfg.map.frame_id:
        logger.warning(
            f"map {path!r} was built in frame {mapper.frame_id!r}, parameter frame_id is "
            f"{cfg.map.frame_id!r}: its voxels are taken as coordinates in {cfg.map.frame_id!r}"
        )
    if cfg.map.frame_id:
        mapper.frame_id = cfg.map.frame_id
    logger.info(f"loaded {mapper.num_voxels} voxels from {path!r} (frame {mapper.frame_id})")
    return mapper, None


FileIdentity = tuple[int, int, int, int]
"""What says a map file is still the one the node loaded or wrote: (device, inode, size,
modification time in ns) of the file, or of a tiled map's ``index.json``."""


def file_identity(path: str) -> FileIdentity | None:
    """The identity of the map at ``path`` (``FileIdentity``), None when there is none."""
    target = os.path.join(path, INDEX_NAME) if os.path.isdir(path) else path
    try:
        st = os.stat(target)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def recovery_path(map_path: str) -> str:
    """Where the node saves when ``map_path`` failed to load: beside it, named by the start
    time (UTC), e.g. ``site.npz`` -> ``site.20261124T010203Z.npz``."""
    stem = map_path.rstrip("/")
    stem = stem[: -len(".npz")] if stem.endswith(".npz") else stem
    return f"{stem}.{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.npz"


def empty_map(cfg: NodeConfig) -> Mapper:
    """A map with nothing in it, as the settings make it, in ``frame_id`` (else "map")."""
    return Mapper.of(cfg.map, cfg.sensor_model, frame_id=cfg.map.frame_id or "map")


class MapFiles:
    """The node's map-file policy (see the module docstring): loads the map at configure,
    serves ``~/save_map``, runs the autosave timer and saves on shutdown."""

    def __init__(self, node: GuardedNode, config: Callable[[], NodeConfig]) -> None:
        self.node = node
        self._config = config
        self._save_lock = threading.Lock()
        self._save_elsewhere: str | None = None  # where saves go when map_path failed to load
        self._saved_version: int | None = None  # the autosave writes only a changed map
        self._worker: LiveIntegrator | None = None
        self._elsewhere_why = "failed to load at start"
        """Why saves go to ``_save_elsewhere``, not ``map_path``."""
        self._on_disk: FileIdentity | None = None
        """``map_path`` as the node loaded or last wrote it (None: no file then)."""

    def load(self) -> Mapper:
        """The map to start from (``initial_mapper``); saves go beside ``map_path`` when it
        failed to load."""
        cfg = self._config()
        self._on_disk = file_identity(cfg.node.map_path) if cfg.node.map_path else None
        mapper, self._save_elsewhere = initial_mapper(cfg, self.node.get_logger())
        self._elsewhere_why = "failed to load at start"
        if cfg.node.autosave_period > 0.0 and not cfg.node.map_path:  # said once, at start
            self.node.get_logger().warning(
                f"autosave_period is {cfg.node.autosave_period:g} s but map_path is empty: "
                "nothing is autosaved (set map_path)"
            )
        return mapper

    def keep(self, worker: LiveIntegrator) -> None:
        """Save ``worker``'s map from now on; its current version counts as saved."""
        self._worker = worker
        self._saved_version = worker.mapper.version

    def create_service(self, group: CallbackGroup) -> Any:
        """``~/save_map`` (created at configure, answered while inactive too)."""
        return self.node.create_service(Trigger, "~/save_map", self._on_save, callback_group=group)

    def create_timer(self, clock: Clock) -> list[Any]:
        """The autosave timer (at activate), when ``autosave_period`` and ``map_path`` are
        set."""
        cfg = self._config()
        if cfg.node.autosave_period > 0.0 and cfg.node.map_path:
            return [
                self.node.create_timer(
                    cfg.node.autosave_period, self._on_autosave_timer, clock=clock
                )
            ]
        return []

    @tracked_role
    async def _on_save(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        """Save in a background thread: writing a large map takes seconds, and meanwhile
        the executor keeps taking odometry and clouds (this call resumes when it is done)."""
        try:
            response.success, response.message = await self.node.off_executor(self.save)
        except Exception as err:  # an unexpected failure answers the call, never kills spin
            self.node.get_logger().error(f"saving the map failed: {err!r}")
            response.success, response.message = False, f"saving failed: {err!r}"
        return response

    def save(self, only_if_changed: bool = False, throttled: bool = False) -> tuple[bool, str]:
        """Write the map to ``map_path`` (one save at a time), or beside it when it failed to
        load at start (``recovery_path``): one map file, or a tiled map when ``map_path`` is
        a directory; stored uncompressed, so that a large map is saved within ``ros2
        launch``'s grace period. Returns (success, message). ``throttled`` (the autosave):
        a failure logs at most one line every few seconds, not one per period."""
        cfg = self._config()
        path = self._save_elsewhere or cfg.node.map_path
        if not path:
            return False, "parameter map_path is empty: nowhere to save"
        worker = self._worker
        assert worker is not None, "keep() comes before a save"
        logger = self.node.get_logger()
        t0 = time.perf_counter()
        try:
            with self._save_lock:
                with worker.whole_map:  # snapshot only: writing runs unlocked
                    started = time.perf_counter() - t0
                    version = worker.mapper.version
                    unchanged = version == self._saved_version
                    if only_if_changed and unchanged:
                        return True, "map unchanged since the last save"
                    arrays = map_blocks(worker.mapper)
                replaced = ""
                if not self._save_elsewhere:
                    on_disk = file_identity(path)
                    replaced = "" if on_disk in (None, self._on_disk) else path
                    if unchanged and replaced:
                        text = (
                            f"map unchanged since loaded or saved and {path!r} was changed on "
                            "disk since the node loaded or wrote it: not written"
                        )
                        logger.info(text)
                        return True, text
                    if replaced:  # someone else's file now: never overwritten
                        path = recovery_path(path)
                count = write_map_path(path, arrays)
                self._saved_version = version
                if not replaced and not self._save_elsewhere:
                    self._on_disk = file_identity(path)
        except (OSError, ValueError, MapFileError) as err:
            if throttled:
                self.node.warn_throttled(
                    "autosave_failed", f"autosaving the map to {path!r} failed: {err}", True
                )
            else:
                logger.error(f"saving the map to {path!r} failed: {err}")
            return False, f"saving to {path!r} failed: {err}"
        seconds = time.perf_counter() - t0
        timing = f"started after {started:.3f} s, done in {seconds:.2f} s"
        kept = ""
        if self._save_elsewhere:
            kept = f" (map_path {cfg.node.map_path!r} {self._elsewhere_why}: kept as it was)"
        if replaced:
            self._save_elsewhere = path  # the later saves go there too, not to a new file
            self._elsewhere_why = "was changed on disk since the node loaded or wrote it"
            kept = (
                f" (map_path {replaced!r} was changed on disk since the node loaded or wrote "
                "it: not overwritten)"
            )
            logger.warning(f"saved {count} voxels to {path!r} ({timing}){kept}")
            return True, f"saved {count} voxels to {path} ({timing}){kept}"
        logger.info(f"saved {count} voxels to {path!r} ({timing}){kept}")
        return True, f"saved {count} voxels to {path} ({timing}){kept}"

    @tracked_role
    def _on_autosave_timer(self) -> None:
        """Save in the background when the map changed, unless a save is running."""
        if self._save_lock.locked():
            return
        self.node.in_background(
            lambda: self.save(only_if_changed=True, throttled=True), "mfp_autosave"
        )

    def save_on_shutdown(self) -> None:
        """Save when ``save_on_shutdown`` (beside ``map_path`` when it failed to load)."""
        if self._config().node.save_on_shutdown:
            self.save()
