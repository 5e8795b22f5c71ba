"""Clouds of first returns paired with the clouds of their second returns (ouster-ros
``points`` and ``points2``): the live node's ``second_return_topic``."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

from mfp_mapper.sensing.pipeline import ReturnPair

PAIR_WAIT = 2
"""Clouds of either kind kept waiting for their partner (the two topics of one lidar are
published together; a first cloud older than this many is mapped alone)."""


def _stamp_key(msg: Any) -> tuple[int, int]:
    stamp = msg.header.stamp
    return int(stamp.sec), int(stamp.nanosec)


class ReturnPairer:
    """Pairs each first-return cloud with the second-return cloud of the same stamp.

    ``first`` and ``second`` take the clouds of either topic as they arrive (any thread)
    and return what is ready for the loop: ``ReturnPair``\\ s, and first clouds whose second
    did not come (mapped alone, counted in ``alone``); a second cloud whose first did not
    come is dropped (``unpaired_second``)."""

    def __init__(self, wait: int = PAIR_WAIT) -> None:
        self._wait = wait
        self._lock = threading.Lock()
        self._first: OrderedDict[tuple[int, int], Any] = OrderedDict()
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
            self._first[key] = msg
            ready = []
            while len(self._first) > self._wait:
                ready.append(self._first.popitem(last=False)[1])
                self.alone += 1
            return ready

    def second(self, msg: Any) -> list[Any]:
        """A second-return cloud arrived: what is ready now."""
        key = _stamp_key(msg)
        with self._lock:
            partner = self._first.pop(key, None)
            if partner is not None:
                self.paired += 1
                return [ReturnPair(partner, msg)]
            self._second[key] = msg
            while len(self._second) > self._wait:
                self._second.popitem(last=False)
                self.unpaired_second += 1
            return []
