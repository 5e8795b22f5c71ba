"""Fleet mapping: many recordings into one map, exactly, in this process or on Dask.

The work is split into tasks: one per recording, or one per time window of a long recording
(``ReplaySection.start``/``end``: half-open windows of cloud stamps that tile the time
axis, so every cloud lands in exactly one task). Each task replays its window with the
same scan pipeline as ``mfp-mapper replay`` (``mapping.replay.replay``) and writes its
partial map as a tiled map (``mapio.tiles``) into a work folder. The reduction is a shuffle
by tile: each reduce task merges one group of tiles of every partial exactly
(``core.merge``: per-voxel sums, each block brought to its latest time with decay), so no
worker holds the whole map. The result equals the sequential replay of all scans up to
the rounding of the summation order.

Without workers, a scheduler or windows, one Mapper takes the recordings in turn in this
process (``map_in_turn``): the same map (decay scales a late scan's data to its block's
time, so the order does not matter up to rounding) at the cost of plain replays, with no
partial maps and no reduction.

A recording that fails (unreadable, no poses...) fails the run, naming it, and nothing is
written; with ``skip_bad`` its partials are dropped and the run goes on. The output (a map
file ``.npz`` or a tiled map directory) is written only at the end, atomically.

Limits: the same input twice is refused (its evidence would count twice) unless
``allow_duplicates``; a recording is cut into at most one window per cloud and
``WINDOWS_PER_WORKER`` windows per worker (a smaller ``chunk_seconds`` is widened, with a
line); a local cluster has at most one worker per task and per CPU core (clamped, with a
line). Scratch folders (``.mfp-fleet-*``) of runs that died (SIGKILL, power loss) are
removed by the next run that uses the same place (``remove_dead_scratch``).
"""

from __future__ import annotations

import math
import os
import resource
import shutil
import socket
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.merge import MergeError, check_mergeable
from mfp_mapper.mapio.loading import is_map_file_name, save_map
from mfp_mapper.mapio.mapfile import MapFileError, map_blocks
from mfp_mapper.mapio.tiles import (
    DEFAULT_TILE_BLOCKS,
    TILE_DIR,
    TiledMap,
    TileEntry,
    TileKey,
    check_tiled_output,
    merge_tile,
    new_generation,
    write_index,
    write_map_file,
    write_tile,
    write_tiled,
)
from mfp_mapper.mapping.executors import Executor, StageProgress, make_executor
from mfp_mapper.mapping.replay import (
    NothingMapped,
    OtherMapFrame,
    ReplayOptions,
    ReplayResult,
    ReplaySummary,
    replay,
)
from mfp_mapper.sources.bags import ReplayError, bag_extent
from mfp_mapper.sources.opener import open_recording
from mfp_mapper.sources.scan_folder import is_scan_folder

SCRATCH_MERGED = "merged"
"""The work folder's tiled map that a ``.npz`` output is assembled from."""
SCRATCH_PREFIX = ".mfp-fleet-"
SCRATCH_OWNER = "owner"
"""File in a scratch folder: ``<host> <pid>`` of the run that made it."""
SCRATCH_STALE_SECONDS = 3600.0
"""A scratch folder of this host with no owner file is removed when untouched this long."""
WINDOWS_PER_WORKER = 16
"""At most this many windows of one recording per worker (``chunk_seconds`` is widened)."""


class FleetError(RuntimeError):
    """The fleet run failed: names the recording and why; no map was written."""


@dataclass(frozen=True)
class Task:
    """Replay of one recording, or of its clouds with stamps in [start, end)."""

    index: int
    recording: str
    start: float | None = None
    end: float | None = None

    @property
    def chunked(self) -> bool:
        return self.start is not None or self.end is not None

    @property
    def label(self) -> str:
        if not self.chunked:
            return self.recording
        lo = "-inf" if self.start is None else f"{self.start:.3f}"
        hi = "inf" if self.end is None else f"{self.end:.3f}"
        return f"{self.recording} [{lo}, {hi}) s"


@dataclass
class TaskResult:
    """What a replay task did: its partial map (None: nothing in its window) and figures."""

    task: Task
    partial: str | None
    tiles: list[TileKey]
    summary: ReplaySummary | None
    note: str = ""
    seconds: float = 0.0
    peak_rss_bytes: int = 0


@dataclass
class FleetOptions:
    """How to run: where (``workers``/``scheduler``; neither: this process), how to split
    recordings (``chunk_seconds``: None = one task per recording) and what to do with a
    failing recording."""

    workers: int | None = None
    scheduler: str | None = None
    chunk_seconds: float | None = None
    skip_bad: bool = False
    tile_blocks: int = DEFAULT_TILE_BLOCKS
    work_dir: str | None = None
    """Folder for the partial maps (every worker must see it); default: beside the output."""
    progress: bool = True
    allow_duplicates: bool = False
    """Map an input given twice twice (its evidence counts twice); refused otherwise."""
    poses: str | None = None
    """Scan folders: ``--poses`` (``identity``, or a file when there is one folder)."""
    times: str | None = None
    """Scan folders: ``--times`` (only with one folder)."""


@dataclass
class FleetResult:
    """The run: tasks, recordings skipped (with ``skip_bad``), the map, times."""

    output: Path
    executor: str
    tasks: list[TaskResult] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    voxels: int = 0
    tiles: int = 0
    seconds_start: float = 0.0
    """Planning, starting the cluster and loading the kernels in its workers."""
    seconds_replay: float = 0.0
    seconds_reduce: float = 0.0
    seconds_write: float = 0.0
    seconds: float = 0.0

    @property
    def summaries(self) -> list[ReplaySummary]:
        return [r.summary for r in self.tasks if r.summary is not None]

    def format(self) -> str:
        sums = self.summaries
        recordings = {r.task.recording for r in self.tasks}
        dropped = Counter[str]()
        for s in sums:
            dropped.update(s.clouds_dropped)
        task_seconds = sum(r.seconds for r in self.tasks)
        lines = [
            f"inputs       {len(recordings)} recordings in {len(self.tasks)} tasks; "
            f"{self.executor}",
            f"scans        {sum(s.scans_used for s in sums):,} used"
            + (f"; dropped {', '.join(f'{k} {v}' for k, v in sorted(dropped.items()))}"
               if dropped else ""),
            f"rays         {sum(s.rays_used for s in sums):,}",
            f"map          {self.output} ({self.voxels:,} voxels"
            + (f" in {self.tiles} tiles)" if self.tiles else ")"),
            f"time         {self.seconds:.2f} s: start {self.seconds_start:.2f} s, "
            f"replay {self.seconds_replay:.2f} s "
            f"({task_seconds:.2f} s of tasks), reduce {self.seconds_reduce:.2f} s, "
            f"write {self.seconds_write:.2f} s",
        ]  # fmt: skip
        lines += [f"skipped      {name}: {why}" for name, why in sorted(self.skipped.items())]
        return "\n".join(lines)


# --- planning ---------------------------------------------------------------------------


def plan_tasks(
    recordings: Sequence[str],
    chunk_seconds: float | None,
    max_windows: int | None = None,
    log: Callable[[str], None] | None = None,
) -> tuple[list[Task], dict[str, str]]:
    """Tasks for ``recordings``; and the recordings that cannot even be opened (why).

    With ``chunk_seconds``, a recording longer than that is split at multiples of it from
    its first message time; the first window is open below and the last open above, so
    windows cover every stamp whatever the clock of the clouds' headers. A recording gets
    at most one window per cloud and ``max_windows`` windows: a smaller ``chunk_seconds``
    is widened for it (said through ``log``). Scan folders are one task each.
    """
    tasks: list[Task] = []
    failed: dict[str, str] = {}
    for recording in recordings:
        bounds: list[float] = []
        if chunk_seconds is not None and chunk_seconds > 0 and not is_scan_folder(recording):
            try:
                first, last, clouds = bag_extent(recording)
            except Exception as err:
                failed[recording] = str(err)
                continue
            chunk = chunk_seconds
            wanted = math.ceil(min((last - first) / chunk_seconds, 1e18))
            limit = max(1, min(clouds, max_windows or clouds))
            if wanted > limit:
                chunk = (last - first) / limit
                if log is not None:
                    log(
                        f"--chunk-seconds {chunk_seconds:g} would cut {recording} into "
                        f"{wanted:,} windows for {clouds:,} clouds: using {chunk:.3g} s "
                        f"({limit} windows)"
                    )
            count = max(1, min(limit, math.ceil((last - first) / chunk)))
            bounds = [first + k * chunk for k in range(1, count)]
        edges: list[float | None] = [None, *bounds, None]
        for lo, hi in zip(edges[:-1], edges[1:], strict=True):
            tasks.append(Task(len(tasks), recording, lo, hi))
    return tasks, failed


# --- the tasks (run in workers) -----------------------------------------------------------


def replay_task(
    task: Task,
    opts: ReplayOptions,
    work_dir: str,
    tile_blocks: int,
    poses: str | None = None,
    times: str | None = None,
) -> TaskResult:
    """Replay ``task`` and write its partial map as tiles under ``work_dir``."""
    t0 = time.perf_counter()
    window = opts.but(  # the task's window within the one asked for (--start/--end), if any
        start=_latest(opts.replay.start, task.start),
        end=_earliest(opts.replay.end, task.end),
    )
    try:
        result = replay_input(task.recording, window, poses, times, progress=False)
    except NothingMapped as err:
        if not task.chunked:
            raise
        return TaskResult(task, None, [], None, note=str(err), seconds=time.perf_counter() - t0)
    try:
        partial = Path(work_dir) / "partials" / f"task{task.index:05d}"
        entries = write_tiled(partial, map_blocks(result.mapper), tile_blocks)
    finally:
        result.mapper.close()
    return TaskResult(
        task,
        str(partial),
        [e.key for e in entries],
        result.summary,
        seconds=time.perf_counter() - t0,
        peak_rss_bytes=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
    )


def replay_input(
    recording: str,
    opts: ReplayOptions,
    poses: str | None,
    times: str | None,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
    on_scan: Callable[..., None] | None = None,
    into: Mapper | None = None,
) -> ReplayResult:
    """Replay a bag or a scan folder (``poses``, ``times``: as ``replay --poses/--times``)."""
    with open_recording(recording, opts, poses, times, log) as opened:
        return replay(opened, opts, progress, log, on_scan, into)


def _latest(a: float | None, b: float | None) -> float | None:
    return b if a is None else a if b is None else max(a, b)


def _earliest(a: float | None, b: float | None) -> float | None:
    return b if a is None else a if b is None else min(a, b)


def reduce_task(
    keys: Sequence[TileKey],
    partials: Sequence[str],
    out_dir: str,
    generation: str,
) -> list[TileEntry]:
    """Merge tiles ``keys`` of the partial maps and write them into ``out_dir``."""
    tiled = [TiledMap(p) for p in partials]
    return [write_tile(out_dir, k, merge_tile(tiled, k), generation) for k in keys]


# --- the run ------------------------------------------------------------------------------


def map_fleet(
    recordings: Sequence[str | Path],
    output: str | Path,
    opts: ReplayOptions | None = None,
    fleet: FleetOptions | None = None,
    log: Callable[[str], None] | None = None,
) -> FleetResult:
    """Map ``recordings`` (bags or scan folders) into ``output`` (``.npz``: one map file;
    otherwise a tiled map directory). FleetError when a recording fails (unless
    ``fleet.skip_bad``), when none could be mapped, when the partial maps cannot be merged
    (other frames...), or when the inputs or options cannot work (said before any mapping)."""
    opts = opts or ReplayOptions()
    fleet = fleet or FleetOptions()
    t0 = time.perf_counter()
    out = Path(output)
    names = check_inputs(recordings, fleet)
    if not is_map_file_name(out):
        try:
            check_tiled_output(out)
        except MapFileError as err:
            raise FleetError(str(err)) from None
    if opts.replay.max_scans is not None and len(names) > 1:
        raise FleetError("max_scans counts the clouds of one replay: use it with one recording")
    if fleet.workers is None and fleet.scheduler is None and not fleet.chunk_seconds:
        return map_in_turn(names, out, opts, fleet, log)
    workers = _worker_count(fleet, names, log)
    max_windows = WINDOWS_PER_WORKER * (workers or 1)
    tasks, failed = plan_tasks(names, fleet.chunk_seconds, max_windows, log)
    if workers is not None and fleet.scheduler is None and workers > len(tasks):
        if log is not None:
            log(f"--workers {workers}: using {len(tasks)}, one per task")
        workers = len(tasks)
    parallel = workers is not None or fleet.scheduler is not None
    if parallel and opts.map.threads <= 0:  # automatic: the worker processes take the cores
        opts = replace(opts, map=replace(opts.map, threads=1))
    evicting = [k for k in ("max_voxels", "keep_radius") if opts.map.core(k) is not None]
    if evicting and len(tasks) > 1:
        raise FleetError(
            f"{' and '.join(evicting)} evict(s) blocks during a replay: partial maps would not "
            "add up to the map of all scans; leave it unset to map several recordings or windows"
        )
    if opts.replay.every != 1 and fleet.chunk_seconds:
        raise FleetError("--every counts the clouds of one replay: not with --chunk-seconds")
    if opts.replay.max_scans is not None and len(tasks) > 1:
        raise FleetError("max_scans counts the clouds of one replay: use it with one recording")
    _fail_or_skip(failed, fleet.skip_bad)
    work = make_scratch(Path(fleet.work_dir) if fleet.work_dir else _parent(out), log)
    try:
        executor = make_executor(workers, fleet.scheduler)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    result = FleetResult(out, executor.description, skipped=dict(failed))
    try:
        executor.warm_up()
        result.seconds_start = time.perf_counter() - t0
        results = _replay_all(executor, tasks, opts, fleet, str(work), result.skipped)
        result.tasks = sorted(results, key=lambda r: r.task.index)
        result.seconds_replay = time.perf_counter() - t0 - result.seconds_start
        partials = [r for r in result.tasks if r.partial is not None]
        if not partials:
            raise FleetError("no cloud could be mapped from any recording (no map written)")
        _check_same_settings(partials)
        t1 = time.perf_counter()
        tiled_out = work / SCRATCH_MERGED if is_map_file_name(out) else out
        generation = new_generation()
        entries = _reduce_all(executor, partials, tiled_out, generation, fleet)
        result.seconds_reduce = time.perf_counter() - t1
        t2 = time.perf_counter()
        settings = TiledMap(partials[0].partial).settings()  # type: ignore[arg-type]
        if is_map_file_name(out):
            write_index(tiled_out, settings, fleet.tile_blocks, entries)
            write_map_file(TiledMap(tiled_out), out)
        else:
            write_index(out, settings, fleet.tile_blocks, entries)
        result.seconds_write = time.perf_counter() - t2
        result.voxels = sum(e.voxels for e in entries)
        result.tiles = len(entries)
    except BaseException:
        if not is_map_file_name(out) and "generation" in locals():
            for stale in (out / TILE_DIR).glob(f"*.{generation}.npz"):
                stale.unlink(missing_ok=True)
        raise
    finally:
        try:
            executor.close()
        finally:
            shutil.rmtree(work, ignore_errors=True)
    result.seconds = time.perf_counter() - t0
    _log_skipped(result, log)
    return result


def map_in_turn(
    names: Sequence[str],
    out: Path,
    opts: ReplayOptions,
    fleet: FleetOptions,
    log: Callable[[str], None] | None = None,
) -> FleetResult:
    """One Mapper takes the recordings in turn, in this process: the fleet's map at the
    cost of plain replays (no partial maps, no reduction). A recording that fails before
    any of its clouds reached the map is skipped with ``skip_bad``; one that fails after
    fails the run (its half could not be taken out again)."""
    t0 = time.perf_counter()
    result = FleetResult(out, "in turn, one mapper in this process")
    mapper: Mapper | None = None
    placed = [0]  # clouds of the current recording handed to the map

    def count(*_: object) -> None:
        placed[0] += 1

    try:
        for index, name in enumerate(names):
            t_task = time.perf_counter()
            placed[0] = 0
            try:
                done = replay_input(
                    name, opts, fleet.poses, fleet.times, fleet.progress, log, count, mapper
                )
            except OtherMapFrame as err:
                raise FleetError(f"{name}: {err} (no map written)") from None
            except Exception as err:
                why = str(err) if isinstance(err, ReplayError) else f"{err!r}"
                if placed[0] and not isinstance(err, NothingMapped):
                    raise FleetError(
                        f"{name}: {why} (after {placed[0]} of its clouds were mapped; "
                        "no map written)"
                    ) from None
                result.skipped[name] = why
                _fail_or_skip({name: why}, fleet.skip_bad)
                continue
            mapper = done.mapper
            result.tasks.append(
                TaskResult(
                    Task(index, name),
                    None,
                    [],
                    done.summary,
                    seconds=time.perf_counter() - t_task,
                    peak_rss_bytes=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                )
            )
        if mapper is None:
            raise FleetError("no cloud could be mapped from any recording (no map written)")
        result.seconds_replay = time.perf_counter() - t0
        t_write = time.perf_counter()
        result.tiles = save_map(mapper, out, fleet.tile_blocks)
        result.seconds_write = time.perf_counter() - t_write
        result.voxels = mapper.num_voxels
    finally:
        if mapper is not None:
            mapper.close()
    result.seconds = time.perf_counter() - t0
    _log_skipped(result, log)
    return result


def _log_skipped(result: FleetResult, log: Callable[[str], None] | None) -> None:
    if log is not None and result.skipped:
        log(f"skipped {len(result.skipped)} recording(s): " + "; ".join(
            f"{k}: {v}" for k, v in sorted(result.skipped.items())))  # fmt: skip


def _parent(out: Path) -> Path:
    return out.parent if str(out.parent) else Path(".")


def check_inputs(recordings: Sequence[str | Path], fleet: FleetOptions) -> list[str]:
    """Absolute input names; FleetError for none, a missing one, the same one twice
    (unless ``allow_duplicates``), or scan-folder options that cannot apply to all."""
    names = [str(Path(r).absolute()) for r in recordings]
    if not names:
        raise FleetError("no recording given")
    seen: dict[str, str] = {}
    for name in names:
        path = Path(name)
        if not path.exists():
            raise FleetError(f"{name}: no such file or folder (no map written)")
        real = str(path.resolve())
        if real in seen and not fleet.allow_duplicates:
            raise FleetError(
                f"{name} is given twice (as {seen[real]}): its evidence would count twice; "
                "--allow-duplicates maps it again"
            )
        seen.setdefault(real, name)
    folders = [n for n in names if is_scan_folder(n)]
    if len(folders) > 1 and fleet.times is not None:
        raise FleetError("--times names the stamps of one scan folder: give one folder with it")
    if len(folders) > 1 and fleet.poses not in (None, "identity"):
        raise FleetError(
            "--poses FILE names the poses of one scan folder: give one folder with it "
            "(or --poses identity, --odometry kiss-icp)"
        )
    if len(folders) < len(names) and (fleet.poses is not None or fleet.times is not None):
        bag = next(n for n in names if n not in folders)
        raise FleetError(f"{bag}: --poses and --times are for folders of scan files")
    return names


def _worker_count(
    fleet: FleetOptions, names: Sequence[str], log: Callable[[str], None] | None
) -> int | None:
    """``fleet.workers`` for a local cluster, at most one per CPU core (said when cut)."""
    if fleet.workers is None or fleet.scheduler is not None:
        return fleet.workers
    if fleet.workers < 1:
        raise FleetError(f"--workers must be at least 1, got {fleet.workers}")
    cores = default_workers()
    if fleet.workers > cores:
        if log is not None:
            log(f"--workers {fleet.workers}: using {cores}, the CPU cores this process may use")
        return cores
    return fleet.workers


def make_scratch(parent: Path, log: Callable[[str], None] | None = None) -> Path:
    """A new scratch folder in ``parent`` (owned by this process, said in its owner file),
    after removing those of dead runs there. FleetError when ``parent`` cannot hold it."""
    if not parent.is_dir():
        raise FleetError(f"work folder {parent}: not an existing directory (no map written)")
    remove_dead_scratch(parent, log)
    try:
        work = Path(tempfile.mkdtemp(prefix=SCRATCH_PREFIX, dir=parent))
        (work / SCRATCH_OWNER).write_text(f"{socket.gethostname()} {os.getpid()}\n")
    except OSError as err:
        if "work" in locals():
            shutil.rmtree(work, ignore_errors=True)
        raise FleetError(
            f"work folder {parent}: cannot write the partial maps there "
            f"({err.strerror or err}); give another with --work-dir (no map written)"
        ) from None
    return work


def remove_dead_scratch(parent: Path, log: Callable[[str], None] | None = None) -> list[Path]:
    """Remove the scratch folders in ``parent`` of runs that died: named ``.mfp-fleet-*``,
    owned by this user, and either made on this host by a process that is gone, or without
    an owner file and untouched for ``SCRATCH_STALE_SECONDS``. Those of other hosts stay."""
    removed: list[Path] = []
    host = socket.gethostname()
    try:
        candidates = list(parent.glob(SCRATCH_PREFIX + "*"))
    except OSError:
        return removed
    for folder in candidates:
        try:
            info = folder.lstat()
            if not folder.is_dir() or folder.is_symlink() or info.st_uid != os.getuid():
                continue
            owner = (folder / SCRATCH_OWNER).read_text().split()
        except FileNotFoundError:
            owner = []
        except OSError:
            continue
        if owner:
            if len(owner) != 2 or owner[0] != host or not owner[1].isdigit():
                continue
            if _process_alive(int(owner[1])):
                continue
        elif time.time() - info.st_mtime < SCRATCH_STALE_SECONDS:
            continue
        shutil.rmtree(folder, ignore_errors=True)
        if not folder.exists():
            removed.append(folder)
    if removed and log is not None:
        log(f"removed {len(removed)} scratch folder(s) of fleet runs that died: "
            + ", ".join(str(f) for f in removed))  # fmt: skip
    return removed


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _fail_or_skip(failed: dict[str, str], skip_bad: bool) -> None:
    if failed and not skip_bad:
        name, why = next(iter(failed.items()))
        named = why if name.split(" [")[0] in why else f"{name}: {why}"
        raise FleetError(f"{named} (no map written; --skip-bad goes on without it)")


def _replay_all(
    executor: Executor,
    tasks: list[Task],
    opts: ReplayOptions,
    fleet: FleetOptions,
    work: str,
    skipped: dict[str, str],
) -> list[TaskResult]:
    """Run the replay tasks; drop the recordings that fail (or raise, without skip_bad)."""
    progress = StageProgress("replay", len(tasks), fleet.progress)
    results: list[TaskResult] = []
    runs = executor.run(replay_task, tasks, opts, work, fleet.tile_blocks, fleet.poses, fleet.times)
    try:
        for done, (task, outcome, error) in enumerate(runs, 1):
            if error is not None:
                why = str(error) if isinstance(error, ReplayError) else f"{error!r}"
                skipped.setdefault(task.recording, why)
                _fail_or_skip({task.label: why}, fleet.skip_bad)
            else:
                results.append(outcome)
            progress.update(done, task.label)
    finally:
        runs.close()  # cancels what is left while the executor still runs
        progress.close()
    mapped = {r.task.recording for r in results if r.partial is not None}
    for r in results:  # every window of a recording empty: nothing of it could be mapped
        if r.task.recording not in mapped and r.task.recording not in skipped:
            skipped[r.task.recording] = r.note
            _fail_or_skip({r.task.recording: r.note}, fleet.skip_bad)
    return [r for r in results if r.task.recording not in skipped]


def _check_same_settings(partials: list[TaskResult]) -> None:
    maps = [TiledMap(r.partial).settings() for r in partials]  # type: ignore[arg-type]
    try:
        check_mergeable(maps, [r.task.label for r in partials])
    except MergeError as err:
        raise FleetError(f"{err} (no map written)") from None


def _reduce_all(
    executor: Executor,
    partials: list[TaskResult],
    out_dir: Path,
    generation: str,
    fleet: FleetOptions,
) -> list[TileEntry]:
    """The shuffle: tiles grouped into about 4 reduce tasks per worker."""
    holders: dict[TileKey, list[str]] = {}
    for r in partials:
        for key in r.tiles:
            holders.setdefault(key, []).append(r.partial)  # type: ignore[arg-type]
    (out_dir / TILE_DIR).mkdir(parents=True, exist_ok=True)
    keys = sorted(holders)
    count = max(1, min(len(keys), 4 * executor.workers))
    groups = [keys[i::count] for i in range(count)]
    jobs = [(group, sorted({p for k in group for p in holders[k]})) for group in groups if group]
    progress = StageProgress("reduce", len(jobs), fleet.progress)
    entries: list[TileEntry] = []
    runs = executor.run(_reduce_job, jobs, str(out_dir), generation)
    try:
        for done, (_, outcome, error) in enumerate(runs, 1):
            if error is not None:
                raise FleetError(f"merging the partial maps failed: {error!r} (no map written)")
            entries.extend(outcome)
            progress.update(done)
    finally:
        runs.close()
        progress.close()
    return entries


def _reduce_job(
    job: tuple[list[TileKey], list[str]], out_dir: str, generation: str
) -> list[TileEntry]:
    keys, partials = job
    return reduce_task(keys, partials, out_dir, generation)


def default_workers() -> int:
    """Worker processes for ``--workers 0``: the CPU cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
