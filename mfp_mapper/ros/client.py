"""A client of a running ``mfp_mapper`` node: its services and ``~/status``, for scripts and
for ``mfp-mapper call`` on machines without the ROS 2 command line.

Every call waits for the node's service (``timeout`` seconds) and for the answer, and raises
``CallError`` with a sentence saying what did not answer; nothing here blocks forever.

A response can be lost in transport right after discovery (Fast DDS: "failed to send
response (timeout)": the node answered before the client's response reader was matched). A
call that changes nothing (query, segments, GetMap, the lifecycle state) is then asked again,
at most ``ATTEMPTS`` times, ``RESEND_AFTER`` seconds after the first request and twice as long
after each next one, the first answer to any of them taken. A call that changes the node
(save, reset, clear-bbox, a lifecycle transition) is asked once: a lost answer does not mean
it was not done (a reset repeated after new scans would forget them; a save takes seconds on
a large map), so the error says so.
"""

from __future__ import annotations

import array
import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import rclpy
import rclpy.context
import rclpy.executors
import rclpy.node
from geometry_msgs.msg import Point
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
from mfp_mapper_msgs.srv import ClearBbox, QueryMap
from nav_msgs.msg import OccupancyGrid
from nav_msgs.srv import GetMap
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Empty, Trigger

DEFAULT_NODE = "mfp_mapper"
DEFAULT_TIMEOUT = 10.0
ATTEMPTS = 3
"""Requests sent at most for a call that changes nothing, when no answer comes."""
RESEND_AFTER = 1.0
"""Seconds without an answer before such a call is asked again (doubled at each retry)."""


class CallError(RuntimeError):
    """A service that did not answer, or answered that it failed."""


@dataclass
class QueryAnswer:
    """``~/query``'s response as plain Python values."""

    success: bool
    message: str
    map_frame_id: str
    points: list[dict[str, Any]]
    segments: list[dict[str, Any]]


def node_path(name: str, namespace: str) -> str:
    """The fully qualified node name (``/ns/name``) of ``name`` in ``namespace``."""
    name = name.strip("/")
    namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return f"{namespace}/{name}"


def _point(xyz: Sequence[float]) -> Point:
    return Point(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


class NodeClient:
    """Calls to the node ``/namespace/name`` in a ROS context of its own (a context manager:
    ``with NodeClient() as client: client.query(...)``)."""

    def __init__(
        self,
        name: str = DEFAULT_NODE,
        namespace: str = "",
        timeout: float = DEFAULT_TIMEOUT,
        args: list[str] | None = None,
    ) -> None:
        if not (math.isfinite(timeout) and timeout > 0.0):
            raise ValueError(f"timeout must be a positive number of seconds, got {timeout}")
        self.target = node_path(name, namespace)
        self.timeout = timeout
        self._context = rclpy.context.Context()
        rclpy.init(args=args, context=self._context)
        self._node = rclpy.node.Node(
            f"mfp_mapper_call_{os.getpid()}", context=self._context, start_parameter_services=False
        )
        self._executor = rclpy.executors.SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)

    def __enter__(self) -> NodeClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Destroy the client node and its context."""
        self._executor.shutdown()
        self._node.destroy_node()
        if self._context.ok():
            rclpy.shutdown(context=self._context)

    # --- plumbing ------------------------------------------------------------------------

    def _call(self, srv_type: Any, service: str, request: Any, idempotent: bool = True) -> Any:
        """The response of ``service`` (relative to the node) to ``request``; ``idempotent``:
        asked again when no answer comes (module docstring), else asked once."""
        name = f"{self.target}/{service}"
        client = self._node.create_client(srv_type, name)
        try:
            deadline = time.monotonic() + self.timeout
            while not client.service_is_ready():
                if time.monotonic() > deadline:
                    raise CallError(
                        f"no service {name} within {self.timeout:g} s: is the node running, "
                        "with this node name and namespace, in this ROS_DOMAIN_ID "
                        f"({os.environ.get('ROS_DOMAIN_ID', '0')})?"
                    )
                self._executor.spin_once(timeout_sec=0.05)
            end = max(deadline, time.monotonic()) + self.timeout
            futures = [client.call_async(request)]
            resend = time.monotonic() + RESEND_AFTER
            while not any(f.done() for f in futures) and time.monotonic() < end:
                if idempotent and len(futures) < ATTEMPTS and time.monotonic() >= resend:
                    futures.append(client.call_async(request))  # the first answer is taken
                    resend = time.monotonic() + RESEND_AFTER * 2 ** (len(futures) - 1)
                self._executor.spin_once(timeout_sec=0.02)
            done = next((f for f in futures if f.done()), None)
            if done is None:
                for future in futures:
                    future.cancel()
                asked = (
                    f"asked {len(futures)} times"
                    if idempotent
                    else "asked once: it changes the node, so a lost answer is not asked "
                    "again; it may have been done (see ~/status)"
                )
                raise CallError(
                    f"{name} did not answer within {self.timeout:g} s ({asked}); is the node "
                    "busy or stopping?"
                )
            for future in futures:
                if future is not done:
                    future.cancel()
            if done.exception() is not None:
                raise CallError(f"{name} failed: {done.exception()}")
            return done.result()
        finally:
            self._node.destroy_client(client)

    # --- the node's services -------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """The node's latest ``~/status`` (JSON counters; latched)."""
        received: list[str] = []
        qos = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        topic = f"{self.target}/status"

        def on_status(msg: Any) -> None:
            received.append(str(msg.data))

        sub = self._node.create_subscription(String, topic, on_status, qos)
        try:
            deadline = time.monotonic() + self.timeout
            while not received and time.monotonic() < deadline:
                self._executor.spin_once(timeout_sec=0.05)
        finally:
            self._node.destroy_subscription(sub)
        if not received:
            raise CallError(f"no {topic} message within {self.timeout:g} s: is the node running?")
        value = json.loads(received[-1])
        if not isinstance(value, dict):
            raise CallError(f"{topic} is not a JSON object")
        return value

    def query(
        self,
        points: Sequence[Sequence[float]] = (),
        segments: Sequence[Sequence[float]] = (),
        frame_id: str = "",
        stamp: float = 0.0,
    ) -> QueryAnswer:
        """``~/query``: statistics at ``points`` (x, y, z) and the clear probability of
        ``segments`` (x0, y0, z0, x1, y1, z1), in ``frame_id`` (empty: the map frame), read at
        ``stamp`` seconds (0: the latest)."""
        xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ends = np.asarray(segments, dtype=np.float64).reshape(-1, 6)
        request = QueryMap.Request()
        request.points_xyz = array.array("d", xyz.tobytes())  # in bulk: one copy
        request.segments_xyz = array.array("d", ends.tobytes())
        request.frame_id = frame_id
        if stamp:
            request.stamp.sec = int(math.floor(stamp))
            request.stamp.nanosec = int(round((stamp - math.floor(stamp)) * 1e9)) % 1_000_000_000
        r = self._call(QueryMap, "query", request)
        rows = [
            {
                "point": xyz[k].tolist(),
                "observed": bool(r.observed[k]),
                "hit_probability": float(r.hit_probability[k]),
                "degree_of_occupancy": float(r.degree_of_occupancy[k]),
                "std": float(r.std[k]),
                "mean_free_path": float(r.mean_free_path[k]),
            }
            for k in range(len(xyz))
            if r.success
        ]
        segs = [
            {
                "start": ends[k, :3].tolist(),
                "end": ends[k, 3:].tolist(),
                "clear_probability": float(r.segment_clear_probability[k]),
                "unknown_length": float(r.segment_unknown_length[k]),
            }
            for k in range(len(ends))
            if r.success
        ]
        return QueryAnswer(bool(r.success), str(r.message), str(r.map_frame_id), rows, segs)

    def get_map(self) -> OccupancyGrid:
        """``~/hit_probability_map`` (nav_msgs/GetMap): the height band's grid."""
        return self._call(GetMap, "hit_probability_map", GetMap.Request()).map

    def save(self) -> tuple[bool, str]:
        """``~/save_map`` (std_srvs/Trigger)."""
        r = self._call(Trigger, "save_map", Trigger.Request(), idempotent=False)
        return bool(r.success), str(r.message)

    def reset(self) -> None:
        """``~/reset`` (std_srvs/Empty): forget the whole map."""
        self._call(Empty, "reset", Empty.Request(), idempotent=False)

    def clear_bbox(
        self, corner_a: Sequence[float], corner_b: Sequence[float]
    ) -> tuple[bool, str, int]:
        """``~/clear_bbox``: reset the voxels whose centres lie in the box to unknown."""
        request = ClearBbox.Request()
        request.min, request.max = _point(corner_a), _point(corner_b)
        r = self._call(ClearBbox, "clear_bbox", request, idempotent=False)
        return bool(r.success), str(r.message), int(r.cleared)

    def lifecycle_state(self) -> str:
        """The node's lifecycle state label (``unconfigured``, ``inactive``, ``active``...)."""
        return str(self._call(GetState, "get_state", GetState.Request()).current_state.label)

    def lifecycle_transitions(self) -> list[str]:
        """The labels of the transitions the node's current state allows."""
        r = self._call(GetAvailableTransitions, "get_available_transitions",
                       GetAvailableTransitions.Request())  # fmt: skip
        return [str(t.transition.label) for t in r.available_transitions]

    def lifecycle_change(self, transition: str) -> bool:
        """Ask for a transition by label (``configure``, ``activate``, ``deactivate``,
        ``cleanup``, ``shutdown``); CallError when the current state does not allow it."""
        allowed = self.lifecycle_transitions()
        label = transition.strip().lower()
        if label == "shutdown":
            label = next((t for t in allowed if t.startswith("shutdown")), label)
        if label not in allowed:
            raise CallError(
                f"{self.target} is {self.lifecycle_state()!r}: transition {transition!r} is "
                f"not allowed from there (allowed: {', '.join(allowed) or 'none'})"
            )
        request = ChangeState.Request()
        request.transition = Transition(label=label)
        return bool(self._call(ChangeState, "change_state", request, idempotent=False).success)
