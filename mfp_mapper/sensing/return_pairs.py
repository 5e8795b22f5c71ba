"""Clouds of first returns paired with the clouds of their second returns (ouster-ros
``points`` and ``points2``, setting ``second_return_topic``): one pairer for the live node
(its clock the wall clock) and for a recording's two topics read offline
(``sources.bags``: its clock the bag's receive times), so that both pair the same clouds and
count them alike."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Any

from mfp_mapper.sensing.pipeline import ReturnPair

PAIR_WAIT = 2
"""Clouds of either kind kept waiting for their partner (the two topics of one lidar are
published together; a first cloud older than this many is mapped alone)."""
PAIR_TIMEOUT = 0.2
"""Seconds a first cloud waits for its second (``expired``): ouster-ros publishes both
within milliseconds; a lidar in single-return mode sends no second."""


def _stamp_key(msg: Any) -> tuple[int, int]:
    stamp = msg.header.stamp
    return int(stamp.sec), int(stamp.nanosec)


def _grid(msg: Any) -> tuple[int, int]:
    return int(msg.height), int(msg.width)


class ReturnPairer:
    """Pairs each first-return cloud with the second-return cloud of the same stamp.

    ``first`` and ``second`` take the clouds of either topic as they arrive (any thread)
    and return what is ready for the loop: ``ReturnPair``\\ s, and first clouds whose second
    did not come (mapped alone, counted in ``alone``: pushed out by newer ones, taken by
    ``expired`` after ``timeout`` s, or by ``flush`` at the end of a recording). A second
    cloud whose first did not come is dropped (``unpaired_second``); one whose pixel grid
    is not its first's is not paired (``mismatched``; ``mismatch_note`` says the first such
    pair's grids) and its first is mapped alone. ``now`` is the time of arrival in seconds
    (default: the wall clock, ``time.monotonic``)."""

    def __init__(self, wait: int = PAIR_WAIT, timeout: float = PAIR_TIMEOUT) -> None:
        self._wait = wait
        self._timeout = timeout
        self._lock = threading.Lock()
        self._first: OrderedDict[tuple[int, int], tuple[float, Any]] = OrderedDict()
        self._second: OrderedDict[tuple[int, int], Any] = OrderedDict()
        self.paired = 0
        self.alone = 0
        self.unpaired_second = 0
        self.mismatched = 0
        self.mismatch_note = ""

    def counts(self) -> dict[str, int]:
        """The counters, by name (the node's ``~/status`` ``second_return``, the replay's
        summary)."""
        with self._lock:
            return {
                "paired": self.paired,
                "alone": self.alone,
                "unpaired_second": self.unpaired_second,
                "mismatched": self.mismatched,
            }

    def first(self, msg: Any, now: float | None = None) -> list[Any]:
        """A first-return cloud arrived: what is ready now."""
        key = _stamp_key(msg)
        with self._lock:
            partner = self._second.pop(key, None)
            if partner is not None:
                return [self._pair(msg, partner)]
            ready = []
            earlier = self._first.pop(key, None)
            if earlier is not None:  # a first cloud of the same stamp: the earlier goes alone
                ready.append(earlier[1])
                self.alone += 1
            self._first[key] = (time.monotonic() if now is None else now, msg)
            while len(self._first) > self._wait:
                ready.append(self._first.popitem(last=False)[1][1])
                self.alone += 1
            return ready

    def expired(self, now: float | None = None) -> list[Any]:
        """The first clouds that waited ``timeout`` s for their second: mapped alone."""
        limit = (time.monotonic() if now is None else now) - self._timeout
        ready = []
        with self._lock:
            while self._first and next(iter(self._first.values()))[0] <= limit:
                ready.append(self._first.popitem(last=False)[1][1])
                self.alone += 1
        return ready

    def second(self, msg: Any, now: float | None = None) -> list[Any]:
        """A second-return cloud arrived: what is ready now (``now`` is unused: a second
        cloud waits only for newer ones to push it out)."""
        key = _stamp_key(msg)
        with self._lock:
            waiting = self._first.pop(key, None)
            if waiting is not None:
                return [self._pair(waiting[1], msg)]
            if self._second.pop(key, None) is not None:  # a second of the same stamp
                self.unpaired_second += 1
            self._second[key] = msg
            while len(self._second) > self._wait:
                self._second.popitem(last=False)
                self.unpaired_second += 1
            return []

    def unreadable_second(self) -> None:
        """A second cloud that could not be read (a damaged message in a bag): counted in
        ``unpaired_second``; its first, if any, will be mapped alone."""
        with self._lock:
            self.unpaired_second += 1

    def flush(self) -> list[Any]:
        """The end of the input: the first clouds still waiting (mapped alone); the second
        clouds still waiting are counted in ``unpaired_second``."""
        with self._lock:
            ready = [msg for _, msg in self._first.values()]
            self.alone += len(ready)
            self.unpaired_second += len(self._second)
            self._first.clear()
            self._second.clear()
        return ready

    def _pair(self, first: Any, second: Any) -> Any:
        """The pair, or the first alone when the grids differ (under the lock)."""
        if _grid(first) == _grid(second):
            self.paired += 1
            return ReturnPair(first, second)
        self.mismatched += 1
        self.alone += 1
        if not self.mismatch_note:
            (h2, w2), (h1, w1) = _grid(second), _grid(first)
            self.mismatch_note = (
                f"a second-return cloud of {h2} x {w2} points for a first-return cloud of "
                f"{h1} x {w1} (stamp {first.header.stamp.sec}.{first.header.stamp.nanosec:09d}):"
                " not paired, the two returns of a pixel must be at the same place of both "
                "clouds; the first returns were mapped alone"
            )
        return first
