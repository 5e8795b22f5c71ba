"""The node's streams (clouds, odometry, TF) taken on a thread of their own, not by rclpy's
executor.

rclpy's Python executor rebuilds its whole wait set (every subscription, service, timer and
event handler of the node: about 40 entities) each time it wakes, and with Fast DDS a
subscription's event handlers (incompatible QoS, ``message_lost``...) wake it at every
message of their subscription, with nothing to run: at 10 clouds and 50 odometry messages a
second the executor woke ~110 times a second and cost ~80 ms of CPU a second (62 ms with
odometry alone, cProfile: 1112 waits in 10 s, 9 in 10 returning nothing ready). rclpy's
``EventsExecutor`` fails here ("Guard conditions not supported"). Here the streams'
subscriptions and their events are waited on in one small wait set of their own, and every
message waiting on a ready subscription is taken at once; the executor keeps everything else
(services, timers, queries): woken by its timers only, it costs ~8 ms a second.

A subscription is created by the node as usual (``Node.create_subscription``, so names,
remapping, QoS and introspection are the same) in ``InputThread.group``, which the executor
runs nothing of. The callbacks run one after the other on this thread, in the order their
messages are taken, so what they share (the pose inputs, the clock watch, the return pairer)
has one writer, as it had on the executor.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack, suppress
from typing import Any, cast

from rclpy.callback_groups import CallbackGroup
from rclpy.context import Context
from rclpy.event_handler import EventHandler
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.subscription import Subscription

WAIT_S = 0.1
"""Longest wait for a message (the thread then checks whether it must stop and ticks)."""
MAX_TAKEN = 64
"""Messages taken from one subscription before the others' are looked at again."""
RESTART_S = 1.0
"""Pause before waiting again after the wait failed (``InputThread._run``)."""
"""Messages taken from one subscription before the others' are looked at again."""


class OwnThreadGroup(CallbackGroup):
    """A callback group the executor never runs anything of: ``InputThread`` takes the
    messages of its subscriptions and their events (``message_lost``, incompatible QoS)."""

    def can_execute(self, entity: Any) -> bool:
        return False

    def beginning_execution(self, entity: Any) -> bool:
        return False

    def ending_execution(self, entity: Any) -> None:
        pass


class InputThread:
    """Takes the messages of ``subscriptions`` (created in ``group``) on a thread of its own
    and calls each one's callback with its message; ``tick`` is called at least every
    ``tick_period`` seconds on that thread too (between messages)."""

    def __init__(
        self,
        context: Context,
        log: Callable[[str], None],
        name: str = "mfp_inputs",
    ) -> None:
        self.group = OwnThreadGroup()
        self._context = context
        self._log = log
        self._name = name
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._guard: GuardCondition | None = None
        self.restarts = 0
        """Times the wait failed and was started again (``_run``)."""

    @property
    def ident(self) -> int | None:
        """The running thread's id (None when not running)."""
        thread = self._thread
        return thread.ident if thread is not None and thread.is_alive() else None

    def start(
        self,
        subscriptions: Sequence[Subscription],
        tick: Callable[[], None] | None = None,
        tick_period: float = WAIT_S,
    ) -> None:
        """Start taking the messages of ``subscriptions`` (stopping a previous run first)."""
        self.stop()
        self._stop = threading.Event()  # its own: a thread that outlived stop() still ends
        self._guard = GuardCondition(None, None, context=self._context)
        self._thread = threading.Thread(
            target=self._run,
            args=(list(subscriptions), self._guard, self._stop, tick, tick_period),
            name=self._name,
            daemon=True,
        )
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and wait for it (a callback running finishes first); the
        subscriptions can then be destroyed."""
        thread, guard = self._thread, self._guard
        if thread is None:
            return
        self._stop.set()
        if guard is not None:
            with suppress(Exception):  # the context is gone: the wait returns by itself
                guard.trigger()
        thread.join(timeout)
        if not thread.is_alive():
            self._thread = None
            if guard is not None:
                guard.destroy()
                self._guard = None

    def _run(
        self,
        subs: list[Subscription],
        guard: GuardCondition,
        stop: threading.Event,
        tick: Callable[[], None] | None,
        tick_period: float,
    ) -> None:
        """``_serve`` until stopped: after a failure while the context is up (a wait that
        raised), the error is logged and the subscriptions are waited on again after
        ``RESTART_S``, so that one fault does not leave the node deaf."""
        while not stop.is_set():
            try:
                self._serve(subs, guard, stop, tick, tick_period)
                return
            except Exception as err:
                if stop.is_set() or not self._context.ok():
                    return  # a handle destroyed or the context shut down meanwhile
                self.restarts += 1
                self._log(
                    f"the input thread failed ({type(err).__name__}: {err}): clouds, odometry"
                    f" and TF are waited on again in {RESTART_S:g} s"
                )
                stop.wait(RESTART_S)

    def _serve(
        self,
        subs: list[Subscription],
        guard: GuardCondition,
        stop: threading.Event,
        tick: Callable[[], None] | None,
        tick_period: float,
    ) -> None:
        """Wait on ``subs``, their events and ``guard`` in a wait set of their own and call
        the callbacks of what is ready, until ``stop`` (raises what the wait raises)."""
        wait_ns = int(min(WAIT_S, tick_period) * 1e9)
        next_tick = time.monotonic() + tick_period
        context = self._context.handle
        if context is None:
            return  # the context is shut down: nothing to wait on
        # (rclpy annotates ``event_handlers`` as one handler: it is their list)
        events = [h for sub in subs for h in cast("list[EventHandler]", sub.event_handlers)]
        wait_set = _rclpy.WaitSet(len(subs), 1, 0, 0, 0, len(events), context)
        try:
            while not stop.is_set():
                with ExitStack() as held:  # nothing destroyed while waited on
                    for sub in subs:
                        held.enter_context(sub.handle)
                    for handler in events:
                        held.enter_context(handler)
                    held.enter_context(guard.handle)
                    held.enter_context(context)
                    wait_set.clear_entities()
                    for sub in subs:
                        wait_set.add_subscription(sub.handle)
                    for handler in events:
                        handler.add_to_wait_set(wait_set)
                    wait_set.add_guard_condition(guard.handle)
                    wait_set.wait(wait_ns)
                    ready = wait_set.get_ready_entities("subscription")
                    happened = [handler for handler in events if handler.is_ready(wait_set)]
                if stop.is_set():
                    return
                for handler in happened:
                    self._call(handler.callback, handler.take_data(), "event")
                for sub in subs:
                    if sub.handle.pointer in ready:
                        self._take(sub)
                if tick is not None and time.monotonic() >= next_tick:
                    next_tick = time.monotonic() + tick_period
                    self._call(lambda _: tick(), True, "tick")
        finally:
            wait_set.destroy_when_not_in_use()

    def _take(self, sub: Subscription) -> None:
        """Every message waiting on ``sub`` (at most ``MAX_TAKEN``), each to its callback
        (a ``tracked`` callback: it raises nothing)."""
        for _ in range(MAX_TAKEN):
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return
            self._call(sub.callback, taken[0], sub.topic_name)

    def _call(self, callback: Callable[[Any], Any], data: Any, what: str) -> None:
        """``callback(data)`` (nothing for no data); an exception is logged, never raised
        (the node's callbacks are ``tracked``: none expected)."""
        if data is None:
            return
        try:
            callback(data)
        except Exception as err:
            self._log(f"{what}: {type(err).__name__}: {err}")
