"""``mfp_mapper.ros.client.NodeClient`` over real DDS against a node whose answers are lost:
a service in this process that takes each request and drops the first answers, as Fast DDS
does right after discovery ("failed to send response (timeout)"). A call that changes
nothing is asked again and gets its answer; one that changes the node is asked once and says
why it was not asked again."""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Iterator
from typing import Any

import pytest

pytestmark = pytest.mark.ros


class LossyNode:
    """A node ``/lossy`` with ``~/query`` and ``~/save_map`` whose first ``lose`` answers
    per service are dropped (the request was taken and answered into nothing)."""

    def __init__(self, lose: int) -> None:
        import rclpy
        import rclpy.context
        import rclpy.executors
        import rclpy.node
        from mfp_mapper_msgs.srv import QueryMap
        from std_srvs.srv import Trigger

        self.asked: Counter[str] = Counter()
        self._context = rclpy.context.Context()
        rclpy.init(context=self._context)
        self._node = rclpy.node.Node("lossy", context=self._context)
        for srv_type, name in ((QueryMap, "query"), (Trigger, "save_map")):
            service = self._node.create_service(
                srv_type, f"~/{name}", lambda req, resp, name=name: self._answer(name, resp)
            )
            send = service.send_response

            def lossy(response: Any, header: Any, name: str = name, send: Any = send) -> None:
                if self.asked[name] > lose:
                    send(response, header)

            service.send_response = lossy  # type: ignore[method-assign]
        self._executor = rclpy.executors.SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self._node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def _answer(self, name: str, response: Any) -> Any:
        self.asked[name] += 1
        response.success = False  # no map behind it: the message says which request
        response.message = f"answer to request {self.asked[name]}"
        return response

    def close(self) -> None:
        import rclpy

        self._executor.shutdown()
        self._thread.join(5.0)
        self._node.destroy_node()
        rclpy.shutdown(context=self._context)


@pytest.fixture
def lossy(ros_domain: int, request: Any) -> Iterator[LossyNode]:
    node = LossyNode(request.param)
    try:
        yield node
    finally:
        node.close()


@pytest.mark.parametrize("lossy", [1], indirect=True)
def test_a_lost_answer_to_a_query_is_asked_again(lossy: LossyNode) -> None:
    from mfp_mapper.ros.client import NodeClient

    with NodeClient("lossy", timeout=10.0) as client:
        answer = client.query(points=[(0.0, 0.0, 0.0)])
    assert answer.message == "answer to request 2", answer
    assert lossy.asked["query"] == 2


@pytest.mark.parametrize("lossy", [1], indirect=True)
def test_a_lost_answer_to_a_save_is_not_asked_again_and_says_so(lossy: LossyNode) -> None:
    from mfp_mapper.ros.client import CallError, NodeClient

    with NodeClient("lossy", timeout=3.0) as client, pytest.raises(CallError) as err:
        client.save()
    assert lossy.asked["save_map"] == 1
    assert "asked once: it changes the node" in str(err.value), err.value
    assert "may have been done" in str(err.value)


@pytest.mark.parametrize("lossy", [100], indirect=True)
def test_a_query_never_answered_is_asked_a_bounded_number_of_times(lossy: LossyNode) -> None:
    from mfp_mapper.ros.client import ATTEMPTS, CallError, NodeClient

    with NodeClient("lossy", timeout=4.0) as client, pytest.raises(CallError) as err:
        client.query(points=[(0.0, 0.0, 0.0)])
    assert lossy.asked["query"] == ATTEMPTS
    assert f"/lossy/query did not answer within 4 s (asked {ATTEMPTS} times)" in str(err.value)
