"""Stopping the node on SIGINT / SIGTERM: cleanly, and without losing the map.

rclpy's own signal handlers shut the context down at once, while the executor may still be
taking a message (a ``take_message`` traceback and exit code 1 during a burst of service
calls). Instead, the node runs with rclpy's handlers off, and ``SpinUntilSignal`` turns the
first SIGINT or SIGTERM into the end of ``spin``: the executor stops between two
callbacks, the node closes (the final save), and only then is rclpy shut down.

``ros2 launch`` escalates: SIGINT, then SIGTERM 5 s later, then SIGKILL 5 s after that.
A signal that arrives while the node is closing is logged and otherwise ignored, so the
save in progress completes (the file is replaced atomically: before the rename, the
previous file is intact; a SIGKILL leaves a temporary file that the next start removes).
Before the node closes, the service calls in flight (a ``~/save_map`` being written) are
answered. Once the node has closed, stop signals are ignored: the process exits 0.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
POLL_S = 0.1
"""Longest time a signal waits for the executor's wait to return (signal handlers run in
the main thread between two waits)."""
ANSWER_S = 60.0
"""Longest wait, after a stop signal, for service calls in flight (a save) to answer."""


class SpinUntilSignal:
    """Install with ``with``: SIGINT / SIGTERM end ``spin``; later ones call ``late``."""

    def __init__(self, log: Callable[[str], None], keep_after_exit: bool = False) -> None:
        self._log = log
        self._keep = keep_after_exit
        self.stop = threading.Event()
        self.signal_name: str | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> SpinUntilSignal:
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            # keep_after_exit: the map is saved, the process ends; a later signal must not
            # turn that into exit -15 (SIG_IGN, unlike a Python handler, outlives the
            # interpreter's finalisation)
            signal.signal(sig, signal.SIG_IGN if self._keep else handler)

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if self.stop.is_set():
            self._log(f"{name} while stopping: finishing the map save first")
            return
        self.signal_name = name
        self.stop.set()
        self._log(f"{name}: stopping")

    def spin(self, executor: Any) -> None:
        """``executor.spin()`` until a stop signal (or the context shuts down)."""
        import rclpy

        while not self.stop.is_set() and rclpy.ok(context=executor.context):
            executor.spin_once(timeout_sec=POLL_S)

    def answer_calls(self, executor: Any, node: Any, timeout: float = ANSWER_S) -> None:
        """After the stop: refuse new work and spin until the service calls in flight (a
        ``~/save_map`` being written) have answered, at most ``timeout`` seconds."""
        import rclpy

        node.refuse_work()
        deadline = time.monotonic() + timeout
        while node.calls_pending and time.monotonic() < deadline:
            if not rclpy.ok(context=executor.context):
                return
            executor.spin_once(timeout_sec=POLL_S)
        if node.calls_pending:
            self._log(f"{node.calls_pending} service call(s) still running after {timeout:g} s")
