"""A ROS 2 node whose callbacks can neither kill its executor nor outlive it.

- ``tracked``: a callback counted in flight (``close`` waits for it), and no exception
  leaves it: it is logged (throttled) and a service answers with its response.
- ``off_executor``: a job run in a thread and awaited, so the executor keeps serving other
  callbacks meanwhile (service callbacks that need the map while a long scan holds it).
- ``warn_throttled``: one log line per key every few seconds.
- ``GuardedLifecycleNode``: the same as an ``rclpy.lifecycle.LifecycleNode``; a transition
  its state machine does not allow from the current state is refused with a log line (rclpy
  raises ``RCLError`` out of ``spin``), and cleanup or shutdown first lets the service calls
  in flight answer: nothing the executor runs outlives its service.
"""

from __future__ import annotations

import functools
import inspect
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import rclpy.task
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node

THROTTLE_S = 5.0


def tracked(callback: Callable[..., Any]) -> Callable[..., Any]:
    """Count a ROS callback as in flight, so close() can wait for it (rclpy's executor
    shutdown does not wait for running callbacks, and destroying a node under a running
    callback can crash the process). Callbacks that start after close() do nothing.

    No exception leaves a callback (it would end ``spin()`` and the node): it is logged and
    a service answers with its (default or error) response.
    """
    return _tracking(callback, lambda owner: owner)


def tracked_role(callback: Callable[..., Any]) -> Callable[..., Any]:
    """``tracked`` for a method of one of the node's roles: an object whose ``node`` is the
    ``GuardedNode`` that counts and logs its callbacks."""
    return _tracking(callback, lambda owner: owner.node)


def _tracking(
    callback: Callable[..., Any], node_of: Callable[[Any], GuardedNode]
) -> Callable[..., Any]:
    def fallback(args: tuple[Any, ...]) -> Any:
        return args[-1] if len(args) == 2 else None  # a service returns its response

    if inspect.iscoroutinefunction(callback):

        @functools.wraps(callback)
        async def run_async(owner: Any, *args: Any) -> Any:
            node = node_of(owner)
            node._call_started()
            try:
                return await callback(owner, *args)
            except Exception as err:
                node._callback_failed(callback.__name__, err)
                return fallback(args)
            finally:  # the executor sends the answer before it runs anything else
                node._call_ended()

        return run_async

    @functools.wraps(callback)
    def run(owner: Any, *args: Any) -> Any:
        node = node_of(owner)
        if not node._begin_work():
            return fallback(args)
        try:
            return callback(owner, *args)
        except Exception as err:
            node._callback_failed(callback.__name__, err)
            return fallback(args)
        finally:
            node._end_work()

    return run


class GuardedNode(Node):
    """A Node with ``tracked`` callbacks, ``off_executor`` jobs and throttled logs."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self._warned: dict[str, float] = {}
        self._closing = False
        self._inflight = 0
        self._inflight_cv = threading.Condition()
        # wakes the executor when a background job finishes (its call resumes)
        self._wake = self.create_guard_condition(lambda: None)
        self._calls = 0  # tracked coroutines (service calls) not yet answered
        self._calls_done: list[rclpy.task.Future] = []  # waiters for calls == 0

    def _call_started(self) -> None:
        self._calls += 1  # executor thread only

    def _call_ended(self) -> None:
        self._calls -= 1
        if self._calls == 0:
            waiters, self._calls_done = self._calls_done, []
            for waiter in waiters:
                waiter.set_result(None)
            self._wake.trigger()

    @property
    def calls_pending(self) -> int:
        """Tracked coroutines (service calls, queries) not yet answered."""
        return self._calls

    async def calls_answered(self) -> None:
        """Wait (in a coroutine on the executor) until every tracked call has returned, so
        that its answer is sent before its service is destroyed."""
        if self._calls == 0:
            return
        waiter = rclpy.task.Future()
        self._calls_done.append(waiter)
        await waiter

    def warn_throttled(self, key: str, text: str, error: bool = False) -> None:
        now = time.monotonic()
        if now - self._warned.get(key, -math.inf) < THROTTLE_S:
            return
        self._warned[key] = now
        # rclpy ties one severity to each call site: keep the two calls apart
        if error:
            self.get_logger().error(text)
        else:
            self.get_logger().warning(text)

    def info_throttled(self, key: str, text: str) -> None:
        """An informational line, at most one per key every few seconds."""
        now = time.monotonic()
        if now - self._warned.get(key, -math.inf) < THROTTLE_S:
            return
        self._warned[key] = now
        self.get_logger().info(text)

    def _callback_failed(self, name: str, err: Exception) -> None:
        self.warn_throttled(
            f"callback_{name}", f"{name} failed: {type(err).__name__}: {err}", error=True
        )

    async def off_executor(self, job: Callable[[], Any]) -> Any:
        """Run ``job`` in a thread and await it: the executor serves other callbacks
        meanwhile. Its exception is raised here."""
        done = rclpy.task.Future()

        def run() -> None:
            try:
                done.set_result((True, job()))
            except Exception as err:
                done.set_result((False, err))
            finally:
                self._end_work()
                self._wake.trigger()

        if not self._begin_work():  # close() waits for the thread, not for this call
            raise RuntimeError("the node is shutting down")
        threading.Thread(target=run, name="mfp_service", daemon=True).start()
        ok, value = await done
        if not ok:
            raise value
        return value

    def in_background(self, job: Callable[[], object], name: str) -> bool:
        """Run ``job`` in a thread of its own, counted in flight (close() waits for it);
        False, and nothing run, once the node closes."""
        if not self._begin_work():
            return False

        def run() -> None:
            try:
                job()
            finally:
                self._end_work()

        threading.Thread(target=run, name=name, daemon=True).start()
        return True

    def _begin_work(self) -> bool:
        """Count work in flight that close() must wait for; False once the node closes."""
        with self._inflight_cv:
            if self._closing:
                return False
            self._inflight += 1
            return True

    def _end_work(self) -> None:
        with self._inflight_cv:
            self._inflight -= 1
            self._inflight_cv.notify_all()

    def wait_idle(self, timeout: float = 10.0) -> None:
        """Refuse new callbacks and wait for those in flight (and their jobs)."""
        with self._inflight_cv:
            self._closing = True
            self._inflight_cv.wait_for(lambda: self._inflight == 0, timeout=timeout)

    def refuse_work(self) -> None:
        """From now on, callbacks do nothing and jobs are refused (until ``reopen``)."""
        with self._inflight_cv:
            self._closing = True

    def reopen(self) -> None:
        """Accept callbacks again after ``wait_idle`` (a lifecycle node configured again)."""
        with self._inflight_cv:
            self._closing = False


class GuardedLifecycleNode(GuardedNode, LifecycleNode):
    """A ``GuardedNode`` that is an ``rclpy.lifecycle.LifecycleNode`` (managed states and
    the ``~/change_state``, ``~/get_state``... services).

    ``~/change_state`` answers ``success: false`` with a warning for a transition the state
    machine does not allow from the current state (an unknown id, configure while active:
    what Nav2's lifecycle manager sends to an autostarted node), where rclpy's own handler
    raises ``RCLError`` out of ``spin``. Before cleanup or shutdown (they destroy the
    services) the calls in flight are answered (``calls_answered``).
    """

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        service = getattr(self, "_service_change_state", None)
        self._rclpy_change_state: Callable[..., Any] | None = None
        if service is not None:  # enable_communication_interface
            self._rclpy_change_state = service.callback
            service.callback = self._on_change_state

    def allowed_transitions(self) -> dict[int, str]:
        """The transitions allowed from the current state: id -> label."""
        return {int(t[0]): str(t[1]) for t in self._state_machine.available_transitions}

    def current_state_label(self) -> str:
        return str(self._state_machine.current_state[1])

    async def _on_change_state(self, request: Any, response: Any) -> Any:
        transition = request.transition
        if not self._allowed(transition):
            response.success = False
            return response
        if transition.id in RELEASING or transition.label in RELEASING_LABELS:
            await self.calls_answered()  # their services are about to be destroyed
            if not self._allowed(transition):  # another transition ran meanwhile
                response.success = False
                return response
        assert self._rclpy_change_state is not None
        try:
            return self._rclpy_change_state(request, response)
        except Exception as err:  # never out of spin
            self.get_logger().error(f"transition {_name(transition)} failed: {err}")
            response.success = False
            return response

    def _allowed(self, transition: Any) -> bool:
        allowed = self.allowed_transitions()
        ok = transition.label in allowed.values() if transition.label else transition.id in allowed
        if not ok:
            choices = ", ".join(f"{label} ({i})" for i, label in sorted(allowed.items()))
            self.get_logger().warning(
                f"transition {_name(transition)} refused: not allowed from state "
                f"{self.current_state_label()!r} (allowed: {choices or 'none'})"
            )
        return ok


RELEASING = frozenset({2, 5, 6, 7})
"""lifecycle_msgs Transition ids that destroy the node's services: cleanup and the three
shutdowns."""
RELEASING_LABELS = frozenset({"cleanup", "shutdown"})


def _name(transition: Any) -> str:
    return repr(transition.label) if transition.label else f"id {transition.id}"
