"""``ros.input_thread``: the messages of the subscriptions of its group, and their events,
reach their callbacks on the input thread, never through the executor; stopped, the
subscriptions can be destroyed; a callback that raises is logged and the thread goes on."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
import rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import wait_for
from std_msgs.msg import String

from mfp_mapper.ros import input_thread
from mfp_mapper.ros.input_thread import InputThread


def test_messages_and_events_reach_their_callbacks_on_the_input_thread(ros_domain: int) -> None:
    node = rclpy.create_node("input_thread_test")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    logged: list[str] = []
    inputs = InputThread(node.context, logged.append)
    got: list[tuple[str, str]] = []  # (data, thread name)
    events: list[str] = []

    def on_message(msg: String) -> None:
        got.append((msg.data, threading.current_thread().name))
        if msg.data == "raise":
            raise RuntimeError("a bad message")

    def on_incompatible(event: Any) -> None:
        events.append(threading.current_thread().name)

    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    sub = node.create_subscription(
        String,
        "input_thread_topic",
        on_message,
        reliable,
        callback_group=inputs.group,
        event_callbacks=SubscriptionEventCallbacks(incompatible_qos=on_incompatible),
    )
    pub = node.create_publisher(String, "input_thread_topic", reliable)
    # a best-effort writer on a reliable reader: an incompatible-QoS event on the reader
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    odd = node.create_publisher(String, "input_thread_topic", best_effort)
    inputs.start([sub])
    try:

        def spin() -> None:
            executor.spin_once(timeout_sec=0.05)

        assert wait_for(lambda: pub.get_subscription_count() > 0, 10.0, spin)
        for text in ("a", "raise", "b", "c"):
            pub.publish(String(data=text))
        assert wait_for(lambda: len(got) == 4 and bool(events), 10.0, spin), (got, events)
        assert [data for data, _ in got] == ["a", "raise", "b", "c"]
        assert {name for _, name in got} == {"mfp_inputs"}
        assert set(events) == {"mfp_inputs"}
        assert any("a bad message" in line for line in logged), logged
        assert inputs.ident is not None
    finally:
        inputs.stop()
    assert inputs.ident is None
    pub.publish(String(data="after the stop"))
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)  # the executor never takes them
    assert [data for data, _ in got] == ["a", "raise", "b", "c"]
    node.destroy_subscription(sub)
    node.destroy_publisher(pub)
    node.destroy_publisher(odd)
    executor.shutdown()
    node.destroy_node()


def test_a_failed_wait_is_logged_and_the_messages_still_come(
    ros_domain: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The first wait set the thread makes raises (a fault in rcl): the error is logged,
    and after ``RESTART_S`` the thread waits again and the messages reach their callback."""
    node = rclpy.create_node("input_thread_restart")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    logged: list[str] = []
    inputs = InputThread(node.context, logged.append)
    got: list[str] = []
    real = input_thread._rclpy
    made = []

    class FirstWaitFails:
        def __getattr__(self, name: str) -> Any:
            return getattr(real, name)

        def WaitSet(self, *args: Any) -> Any:  # noqa: N802 (rclpy's name)
            made.append(args)
            if len(made) == 1:
                raise RuntimeError("injected wait-set failure")
            return real.WaitSet(*args)

    monkeypatch.setattr(input_thread, "_rclpy", FirstWaitFails())
    monkeypatch.setattr(input_thread, "RESTART_S", 0.2)
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    sub = node.create_subscription(
        String,
        "input_restart_topic",
        lambda m: got.append(m.data),
        reliable,
        callback_group=inputs.group,
    )
    pub = node.create_publisher(String, "input_restart_topic", reliable)
    inputs.start([sub])
    try:

        def spin() -> None:
            executor.spin_once(timeout_sec=0.05)

        assert wait_for(lambda: pub.get_subscription_count() > 0 and len(made) >= 2, 10.0, spin)
        pub.publish(String(data="after the fault"))
        assert wait_for(lambda: got == ["after the fault"], 10.0, spin), got
        assert inputs.restarts == 1
        assert any("injected wait-set failure" in line for line in logged), logged
    finally:
        inputs.stop()
    assert inputs.ident is None
    node.destroy_subscription(sub)
    node.destroy_publisher(pub)
    executor.shutdown()
    node.destroy_node()
