"""The node's /tf path per message under a flood (issue 32 item 14): 100 new frames a
message, after 60,000 churned names, as ``test_clouds_flow_under_a_tf_flood_after_a_churn``
sends them. Three ways, interleaved over rounds, each on a tree of its own:

- ``objects+add``: rclpy's deserialization into message objects, then ``TfTree.add`` per
  transform (numpy-checked arguments): the node's path before the raw subscription;
- ``objects+records``: rclpy's deserialization, then ``TfTree.add_records``;
- ``raw+records``: ``ros.tf_cdr.tf_records`` on the CDR bytes, then ``add_records``: the
  node's path now.

Prints CPU milliseconds of the calling thread per message (``time.thread_time``: a loaded
machine's descheduling left out; the garbage collector's passes, which a heap of 60,000
frames makes costly, counted), median of the rounds, and the ratio to ``objects+add``.

    python benchmarks/bench_tf_flood.py [--rounds 5] [--messages 150]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

from geometry_msgs.msg import TransformStamped
from rclpy.serialization import deserialize_message, serialize_message
from tf2_msgs.msg import TFMessage

from mfp_mapper.ros.tf_cdr import tf_records
from mfp_mapper.sensing.pointcloud import stamp_seconds
from mfp_mapper.sensing.tf_tree import TfTree, transform_records

T0 = 1000.0


def message(stamp: float, names: list[str]) -> bytes:
    tfs = []
    for name in names:
        tf = TransformStamped()
        tf.header.frame_id, tf.child_frame_id = "map", name
        tf.header.stamp.sec, tf.header.stamp.nanosec = int(stamp), int(stamp % 1 * 1e9)
        tf.transform.rotation.w = 1.0
        tfs.append(tf)
    return serialize_message(TFMessage(transforms=tfs))


def churned_tree() -> TfTree:
    tree = TfTree(buffer_length=10.0)
    for k in range(600):
        for j in range(100):
            tree.add("map", f"churn_{k}_{j}", T0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    return tree


def objects_add(tree: TfTree, data: bytes) -> None:
    for tf in deserialize_message(data, TFMessage).transforms:
        tr, rot = tf.transform.translation, tf.transform.rotation
        tree.add(tf.header.frame_id, tf.child_frame_id, stamp_seconds(tf.header.stamp),
                 (tr.x, tr.y, tr.z), (rot.x, rot.y, rot.z, rot.w), now=T0 + 1.0)  # fmt: skip


def objects_records(tree: TfTree, data: bytes) -> None:
    tree.add_records(transform_records(deserialize_message(data, TFMessage)), False, T0 + 1.0)


def raw_records(tree: TfTree, data: bytes) -> None:
    tree.add_records(tf_records(data), False, T0 + 1.0)


WAYS: dict[str, Callable[[TfTree, bytes], None]] = {
    "objects+add": objects_add,
    "objects+records": objects_records,
    "raw+records": raw_records,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--messages", type=int, default=150)
    args = parser.parse_args()
    flood = [
        message(T0 + 0.01 * (k % 10), [f"flood_{k}_{i}" for i in range(100)])
        for k in range(args.messages)
    ]
    ms: dict[str, list[float]] = {way: [] for way in WAYS}
    for _ in range(args.rounds):
        for way, run in WAYS.items():
            tree = churned_tree()
            t0 = time.thread_time()
            for data in flood:
                run(tree, data)
            ms[way].append(1e3 * (time.thread_time() - t0) / len(flood))
    base = statistics.median(ms["objects+add"])
    for way, values in ms.items():
        m = statistics.median(values)
        print(f"{way:16s} {m:6.3f} CPU ms/message (100 transforms)  x{base / m:5.2f} "
              f"vs objects+add [{min(values):.3f}-{max(values):.3f}]")  # fmt: skip


if __name__ == "__main__":
    main()
