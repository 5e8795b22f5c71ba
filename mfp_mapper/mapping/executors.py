"""Where fleet tasks run: in this process, one after the other, or on a Dask cluster.

Dask (``dask``, ``distributed``) is imported here only, when a cluster is asked for: it is a
dependency of the offline tools, never of the node.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Generator, Sequence
from typing import Any, TextIO

from mfp_mapper.mapping.progress import stderr_bar

Outcome = tuple[Any, Any, BaseException | None]
"""(item, result, error): exactly one of result and error is meaningful."""
Runs = Generator[Outcome, None, None]
"""The outcomes as tasks finish; ``close()`` it to cancel the rest."""


UNSET_IN_WORKERS = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"


class SequentialExecutor:
    """Runs each task here, in order (no Dask needed)."""

    description = "sequential, in this process"
    workers = 1

    def run(self, fn: Callable[..., Any], items: Sequence[Any], *args: Any) -> Runs:
        for item in items:
            try:
                yield item, fn(item, *args), None
            except Exception as err:
                yield item, None, err

    def warm_up(self) -> None:
        pass

    def close(self) -> None:
        pass


class DaskExecutor:
    """Runs tasks on a Dask distributed cluster: a new LocalCluster of ``workers`` processes
    (one thread each), or the cluster whose scheduler listens at ``scheduler``."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None) -> None:
        try:
            from distributed import Client, LocalCluster
        except ImportError as err:  # pragma: no cover - depends on the installation
            raise RuntimeError(
                f"Dask is needed for --workers/--scheduler ({err}): pip install dask distributed"
            ) from None
        self._cluster: Any = None
        if scheduler is not None:
            try:
                self.client = Client(scheduler, timeout="20s")
            except OSError as err:
                raise RuntimeError(
                    f"cannot reach the Dask scheduler at {scheduler}: {err}"
                ) from None
            self.workers = max(1, len(self.client.scheduler_info().get("workers", {})))
            self.description = f"Dask cluster at {scheduler} ({self.workers} workers)"
        else:
            import dask

            count = max(1, int(workers or 1))
            # Dask sets MALLOC_TRIM_THRESHOLD_=65536 in its workers, which makes glibc hand
            # large freed arrays back at once and fault them in again: the replay ran 45%
            # slower in such a worker (measured). Not set here.
            with dask.config.set({UNSET_IN_WORKERS: None}):
                self._cluster = LocalCluster(
                    n_workers=count,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=":0",  # any free port: no clash with another run's
                    silence_logs=logging.CRITICAL,  # a failing task is reported by the run
                )
            self.client = Client(self._cluster)
            self.workers = count
            self.description = f"Dask LocalCluster, {count} worker processes"

    def warm_up(self) -> None:
        """Load the core's compiled kernels in every worker now, all at once."""
        self.client.run(warm_up_worker)

    def run(self, fn: Callable[..., Any], items: Sequence[Any], *args: Any) -> Runs:
        from distributed import as_completed

        futures = {
            self.client.submit(fn, item, *args, pure=False, retries=0): item for item in items
        }
        try:
            for future in as_completed(list(futures)):
                item = futures[future]
                if future.status == "error":
                    yield item, None, future.exception()
                else:
                    yield item, future.result(), None
        finally:  # stopped early (a failure): the rest is not wanted
            pending = [f for f in futures if not f.done()]
            if pending and self.client.status == "running":
                with contextlib.suppress(RuntimeError, OSError):  # the client is closing
                    self.client.cancel(pending)

    def close(self) -> None:
        """Close the client and our cluster; a slow shutdown (workers still busy on a loaded
        machine, a timeout) is not an error of the run: the processes are ended anyway."""
        with contextlib.suppress(Exception):
            self.client.close()
        if self._cluster is not None:
            with contextlib.suppress(Exception):
                self._cluster.close()


Executor = SequentialExecutor | DaskExecutor


def warm_up_worker() -> None:
    """Import the replay and run the core once on a few rays (numba loads its kernels)."""
    import numpy as np

    from mfp_mapper.core.mapper import Mapper
    from mfp_mapper.mapping import replay  # noqa: F401  (the task's imports)

    mapper = Mapper(0.5)
    mapper.integrate(np.array([[2.0, 0.5, 0.3]]), np.zeros(3), 0.0)
    mapper.voxels()


def make_executor(workers: int | None = None, scheduler: str | None = None) -> Executor:
    """Dask when ``workers`` or ``scheduler`` is given, else this process."""
    if scheduler is not None or workers is not None:
        return DaskExecutor(workers, scheduler)
    return SequentialExecutor()


class StageProgress:
    """A progress line per stage on stderr (tqdm): tasks done of all, time elapsed and left,
    the task that finished last. Redrawn in place on a terminal; elsewhere every 5 s."""

    def __init__(
        self, stage: str, total: int, enabled: bool = True, stream: TextIO | None = None
    ) -> None:
        self._bar: Any = stderr_bar(
            stage,
            total,
            "{desc} {n_fmt}/{total_fmt} tasks  elapsed {elapsed}  left {remaining}  {postfix}",
            enabled,
            stream,
        )

    def update(self, done: int, note: str = "") -> None:
        """``done`` tasks so far; ``note`` names the last one."""
        if self._bar.disable:
            return
        self._bar.set_postfix_str(f"({note})" if note else "", refresh=False)
        self._bar.update(done - self._bar.n)
        if done >= self._bar.total:
            self._bar.close()

    def close(self) -> None:
        self._bar.close()
