"""Clouds of first returns paired with the clouds of their second returns (ouster-ros
``points`` and ``points2``): the live node's ``second_return_topic``."""

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
"""Seconds (wall clock) a first cloud waits for its second (``expired``): ouster-ros
publishes both within milliseconds; a lidar in single-return mode sends no second."""


def _stamp_key(msg: Any) -> tuple[int, int]:
    stamp = msg.header.stamp
    return int(stamp.sec), int(stamp.nanosec)


class ReturnPairer:
    """Pairs each first-return cloud with the second-return cloud of the same stamp.

    ``first`` and ``second`` take the clouds of either topic as they arrive (any thread)
    and return what is ready for the loop: ``ReturnPair``\\ s, and first clouds whose second
    did not come (mapped alone, counted in ``alone``: pushed out by newer ones, or taken by
    ``expired`` after ``timeout`` s); a second cloud whose first did not come is dropped
    (``unpaired_second``)."""

    def __init__(self, wait: int = PAIR_WAIT, timeout: float = PAIR_TIMEOUT) -> None:
        self._wait = wait
        self._timeout = timeout
        self._lock = threading.Lock()
        self._first: OrderedDict[tuple[int, int], tuple[float, Any]] = OrderedDict()
        self._second: OrderedDict[tuple[int, int], Any] = OrderedDict()
        self.paired = 0
        self.alone = 0
        self.unpaired_second = 0

    def first(self, msg: Any) -> list[Any]:
        """A first-return cloud arrived: what is ready now."""
        key = _stamp_key(msg)
        with self._lock:
            partner = self._second.pop(key, None)
            if partner is not None:
                self.paired += 1
                return [ReturnPair(msg, partner)]
            self._first[key] = (time.monotonic(), msg)
            ready = []
            while len(self._first) > self._wait:
                ready.append(self._first.popitem(last=False)[1][1])
                self.alone += 1
            return ready

    def expired(self) -> list[Any]:
        """The first clouds that waited ``timeout`` s for their second: mapped alone."""
        limit = time.monotonic() - self._timeout
        ready = []
        with self._lock:
            while self._first and next(iter(self._first.values()))[0] <= limit:
                ready.append(self._first.popitem(last=False)[1][1])
                self.alone += 1
        return ready

    def second(self, msg: Any) -> list[Any]:
        """A second-return cloud arrived: what is ready now."""
        key = _stamp_key(msg)
        with self._lock:
            waiting = self._first.pop(key, None)
            if waiting is not None:
                self.paired += 1
                return [ReturnPair(waiting[1], msg)]
            self._second[key] = msg
            while len(self._second) > self._wait:
                self._second.popitem(last=False)
                self.unpaired_second += 1
            return []
