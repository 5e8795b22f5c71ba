"""The two locks of a map shared between the live worker and the node's services."""

from __future__ import annotations

import threading
from types import TracebackType

MERGE_PAUSE_S = 0.0005
"""How long a merge lets go of the map between two chunks (a waiting reader takes it)."""


class WholeMap:
    """``with whole_map:`` the map lock, at a time no scan is half merged.

    The worker holds ``gate`` through a merge (``Mapper.commit``) and ``lock`` except
    between two chunks of it; a reader that needs whole scans (GetMap, saving) or replaces
    the map (reset) takes both, a query ``lock`` alone.
    """

    def __init__(self, gate: threading.Lock, lock: threading.Lock) -> None:
        self.gate = gate
        self.lock = lock

    def __enter__(self) -> WholeMap:
        self.gate.acquire()
        try:
            self.lock.acquire()
        except BaseException:
            self.gate.release()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.lock.release()
        self.gate.release()
