"""The replay's progress line on stderr (tqdm): scans done, rays/s, time elapsed and left."""

from __future__ import annotations

import sys
from typing import Any, TextIO


def stderr_bar(
    desc: str,
    total: int,
    bar_format: str,
    enabled: bool = True,
    stream: TextIO | None = None,
    interval: float | None = None,
) -> Any:
    """A tqdm bar on ``stream`` (stderr): redrawn in place every 0.2 s on a terminal,
    elsewhere (logs, CI) a line every 5 s; ``enabled=False`` prints nothing."""
    from tqdm import tqdm

    stream = stream or sys.stderr
    tty = bool(getattr(stream, "isatty", lambda: False)())
    return tqdm(
        total=max(total, 0),
        file=stream,
        disable=not enabled,
        mininterval=interval if interval is not None else (0.2 if tty else 5.0),
        desc=desc,
        dynamic_ncols=tty,
        bar_format=bar_format,
    )


class Progress:
    """A progress bar of ``total`` scans; ``update(done, rays)`` sets its state.

    On a terminal it redraws in place every ``interval`` s (0.2 by default); elsewhere
    (logs, CI) every 5 s. ``enabled=False`` prints nothing.
    """

    def __init__(
        self,
        total: int,
        stream: TextIO | None = None,
        enabled: bool = True,
        interval: float | None = None,
    ) -> None:
        self._bar: Any = stderr_bar(
            "replay",
            total,
            "{desc} [{bar:24}] {n_fmt}/{total_fmt} scans  {postfix}  "
            "elapsed {elapsed}  left {remaining}",
            enabled,
            stream,
            interval,
        )
        self._rays = 0

    def update(self, done: int, rays: int, force: bool = False) -> None:
        """Scans ``done`` so far and ``rays`` integrated so far; ``force`` redraws now."""
        bar = self._bar
        if bar.disable:
            return
        elapsed = bar.format_dict["elapsed"]
        rate = rays / elapsed if elapsed > 0 else 0.0
        bar.set_postfix_str(f"{rays / 1e6:.2f} M rays  {rate / 1e3:,.0f} k rays/s", refresh=False)
        bar.update(done - bar.n)
        if force:
            bar.refresh()

    def close(self) -> None:
        self._bar.close()
