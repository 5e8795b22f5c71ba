"""The project's own TF buffer (no tf2_ros): static and dynamic transforms, chain lookups.

Frames form a tree: each child frame has one parent. Static edges (``/tf_static``) hold one
transform for all time; dynamic edges (``/tf``) hold samples over the last
``buffer_length`` seconds, interpolated at lookup (translation linear, rotation slerp).
A lookup of ``target <- source`` walks both frames up to their common ancestor and composes
the edges at each requested stamp, so a whole scan is looked up at once for de-skew.

Stamps are checked against the stream: a sample more than ``max_jump`` seconds ahead of its
edge's latest is held back until a second one confirms the jump (one poisoned stamp cannot
push the buffer into the future), a sample older than the buffer is dropped, and with a
reference clock (``now``) a sample more than ``max_future`` seconds ahead of it is rejected.
:meth:`TfTree.observe_clock` clears the dynamic edges when the clock jumps back (tf2 does
the same). Quaternions are ``(x, y, z, w)``; ``T_a_b`` maps points in ``b`` into ``a``.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mfp_mapper.sensing.pointcloud import stamp_seconds
from mfp_mapper.sensing.poses import (
    IDENTITY_QUATERNION,
    PoseUnavailable,
    interpolate_samples,
    normalize_quaternion,
    quaternion_to_matrix,
)

FloatArray = NDArray[np.float64]
_MAX_DEPTH = 64


class TransformUnavailable(PoseUnavailable):
    """No transform for a lookup. Reasons: those of PoseUnavailable (``"no_poses"``,
    ``"too_new"``, ``"too_old"``, ``"gap"``, each naming the edge) and ``"unconnected"``
    (no chain between the frames, or an unknown frame)."""


def quaternion_multiply(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Hamilton product ``a * b`` (xyzw, broadcast): rotate by ``b`` then by ``a``."""
    x1, y1, z1, w1 = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    x2, y2, z2, w2 = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ],
        -1,
    )


def quaternion_rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """Vectors ``v`` (..., 3) rotated by unit quaternions ``q`` (..., 4)."""
    quat = np.asarray(q, dtype=np.float64)
    vec = np.asarray(v, dtype=np.float64)
    u, w = quat[..., :3], quat[..., 3:]
    uv = np.cross(u, vec)
    return vec + 2.0 * (w * uv + np.cross(u, uv))


def compose(
    outer: tuple[FloatArray, FloatArray], inner: tuple[FloatArray, FloatArray]
) -> tuple[FloatArray, FloatArray]:
    """``T_a_c`` from ``T_a_b`` (outer) and ``T_b_c`` (inner), as (translation, quaternion)."""
    t_ab, q_ab = outer
    t_bc, q_bc = inner
    return quaternion_rotate(q_ab, t_bc) + t_ab, quaternion_multiply(q_ab, q_bc)


def invert(transform: tuple[FloatArray, FloatArray]) -> tuple[FloatArray, FloatArray]:
    """``T_b_a`` from ``T_a_b``."""
    t, q = transform
    q_inv = q * np.array([-1.0, -1.0, -1.0, 1.0])
    return -quaternion_rotate(q_inv, t), q_inv


@dataclass
class _Edge:
    """Samples of one dynamic edge (child in parent), sorted by stamp."""

    parent: str
    stamps: list[float] = field(default_factory=list)
    translations: list[FloatArray] = field(default_factory=list)
    quaternions: list[FloatArray] = field(default_factory=list)
    pending: float | None = None
    _arrays: tuple[FloatArray, FloatArray, FloatArray] | None = None

    def insert(self, stamp: float, t: FloatArray, q: FloatArray, buffer_length: float) -> None:
        i = bisect_left(self.stamps, stamp)
        if i < len(self.stamps) and self.stamps[i] == stamp:
            self.translations[i], self.quaternions[i] = t, q
        else:
            self.stamps.insert(i, stamp)
            self.translations.insert(i, t)
            self.quaternions.insert(i, q)
        drop = bisect_left(self.stamps, self.stamps[-1] - buffer_length) - 1
        if drop > 0:
            del self.stamps[:drop], self.translations[:drop], self.quaternions[:drop]
        self._arrays = None

    def arrays(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        if self._arrays is None:
            quats = np.array(self.quaternions)
            # one hemisphere between neighbours, so slerp takes the short way
            signs = np.sign(np.einsum("ij,ij->i", quats[:-1], quats[1:]))
            flip = np.concatenate([[1.0], np.cumprod(np.where(signs < 0.0, -1.0, 1.0))])
            self._arrays = (
                np.array(self.stamps),
                np.array(self.translations),
                quats * flip[:, None],
            )
        return self._arrays


class TfTree:
    """Static and dynamic transforms, looked up as chains at one or many stamps."""

    def __init__(
        self,
        buffer_length: float = 10.0,
        max_gap: float = math.inf,
        max_jump: float = 5.0,
        max_future: float = 10.0,
    ) -> None:
        if not (buffer_length > 0 and max_gap > 0 and max_jump > 0 and max_future > 0):
            raise ValueError("buffer_length, max_gap, max_jump and max_future must be > 0")
        self.buffer_length = float(buffer_length)
        self.max_gap = float(max_gap)
        self.max_jump = float(max_jump)
        self.max_future = float(max_future)
        self.rejected: Counter[str] = Counter()
        """Samples not stored, by reason: invalid, old, future_outlier, ahead_of_clock."""
        self._static: dict[str, tuple[str, FloatArray, FloatArray]] = {}
        self._dynamic: dict[str, _Edge] = {}
        self._last_clock: float | None = None

    # --- input ---------------------------------------------------------------------------

    def add_message(self, msg: Any, static: bool, now: float | None = None) -> int:
        """Add every transform of a tf2_msgs/TFMessage (rclpy or rosbags); how many stored."""
        stored = 0
        for tf in msg.transforms:
            tr, rot = tf.transform.translation, tf.transform.rotation
            stored += self.add(
                str(tf.header.frame_id),
                str(tf.child_frame_id),
                stamp_seconds(tf.header.stamp),
                (tr.x, tr.y, tr.z),
                (rot.x, rot.y, rot.z, rot.w),
                static=static,
                now=now,
            )
        return stored

    def add(
        self,
        parent: str,
        child: str,
        stamp: float,
        translation: ArrayLike,
        quaternion_xyzw: ArrayLike,
        static: bool = False,
        now: float | None = None,
    ) -> bool:
        """Store ``T_parent_child``; False (counted in ``rejected``) when it is not stored."""
        parent, child = normalize_frame(parent), normalize_frame(child)
        t = np.asarray(translation, dtype=np.float64).reshape(-1)
        try:
            q = normalize_quaternion(quaternion_xyzw)
        except ValueError:
            q = None
        if q is None or t.shape != (3,) or not np.all(np.isfinite(t)) or not math.isfinite(stamp):
            self.rejected["invalid"] += 1
            return False
        if not parent or not child or parent == child:
            self.rejected["invalid"] += 1
            return False
        if static:
            self._static[child] = (parent, t, q)
            self._dynamic.pop(child, None)
            return True
        if now is not None and stamp > now + self.max_future:
            self.rejected["ahead_of_clock"] += 1
            return False
        edge = self._dynamic.get(child)
        if edge is None or edge.parent != parent:
            edge = self._dynamic[child] = _Edge(parent)
        if not self._plausible(edge, stamp):
            return False
        edge.insert(float(stamp), t, q, self.buffer_length)
        return True

    def _plausible(self, edge: _Edge, stamp: float) -> bool:
        if not edge.stamps:
            return True
        latest = edge.stamps[-1]
        if stamp < latest - self.buffer_length:
            self.rejected["old"] += 1
            return False
        if stamp <= latest + self.max_jump:
            edge.pending = None
            return True
        # far ahead of the stream: accept only when a second sample confirms the jump
        confirmed = edge.pending is not None and abs(stamp - edge.pending) <= self.max_jump
        edge.pending = None if confirmed else stamp
        if not confirmed:
            self.rejected["future_outlier"] += 1
        return confirmed

    def snapshot(self) -> TfTree:
        """A copy that later ``add`` calls leave unchanged (lookups outside a lock)."""
        copy = TfTree(self.buffer_length, self.max_gap, self.max_jump, self.max_future)
        copy._static = dict(self._static)
        copy._dynamic = {
            child: _Edge(
                e.parent,
                list(e.stamps),
                list(e.translations),
                list(e.quaternions),
                e.pending,
                e._arrays,
            )
            for child, e in self._dynamic.items()
        }
        return copy

    def observe_clock(self, now: float) -> bool:
        """Note the reference clock; True (dynamic edges cleared) when it jumped back."""
        jumped = self._last_clock is not None and now < self._last_clock
        self._last_clock = now
        if jumped:
            self.clear()
        return jumped

    def clear(self, static: bool = False) -> None:
        """Forget the dynamic samples (and the static edges too with ``static``)."""
        self._dynamic.clear()
        if static:
            self._static.clear()

    # --- structure -----------------------------------------------------------------------

    def frames(self) -> set[str]:
        """Every frame named by a stored edge."""
        names = set(self._static) | set(self._dynamic)
        names |= {p for p, _, _ in self._static.values()}
        return names | {e.parent for e in self._dynamic.values()}

    def parent(self, child: str) -> tuple[str, bool] | None:
        """The parent of ``child`` and whether the edge is static; None at a root."""
        child = normalize_frame(child)
        if child in self._dynamic:
            return self._dynamic[child].parent, False
        if child in self._static:
            return self._static[child][0], True
        return None

    def ancestors(self, frame: str) -> list[str]:
        """``frame`` then its parents up to its root."""
        chain = [normalize_frame(frame)]
        while (up := self.parent(chain[-1])) is not None:
            if up[0] in chain or len(chain) > _MAX_DEPTH:
                raise TransformUnavailable("unconnected", f"TF has a loop through {up[0]!r}")
            chain.append(up[0])
        return chain

    def static_chain(self, top: str, bottom: str) -> tuple[FloatArray, FloatArray] | None:
        """``T_top_bottom`` through static edges only; None when they do not connect."""
        top, frame = normalize_frame(top), normalize_frame(bottom)
        t, q = np.zeros(3), np.array(IDENTITY_QUATERNION)
        for _ in range(_MAX_DEPTH):
            if frame == top:
                return t, q
            if frame not in self._static or frame in self._dynamic:
                return None
            parent, te, qe = self._static[frame]
            t, q = compose((te, qe), (t, q))
            frame = parent
        return None

    def edge_stamps(self, child: str) -> FloatArray:
        """Stamps of the dynamic edge above ``child`` (empty when static or unknown)."""
        edge = self._dynamic.get(normalize_frame(child))
        return np.array(edge.stamps) if edge is not None else np.zeros(0)

    def is_dynamic(self, child: str) -> bool:
        """Whether the edge above ``child`` comes from /tf (moves)."""
        return normalize_frame(child) in self._dynamic

    def latest_common_stamp(self, target: str, source: str) -> float | None:
        """Latest stamp at which the chain can be looked up (None: static only or unknown)."""
        path = self._path(target, source)
        latest = [self._dynamic[c].stamps[-1] for c, _ in path if c in self._dynamic]
        return min(latest) if latest else None

    # --- lookup --------------------------------------------------------------------------

    def lookup(self, target: str, source: str, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``T_target_source`` at each stamp: translations (N, 3) and quaternions (N, 4).

        Raises TransformUnavailable naming the frames (and the edge that is missing)."""
        times = np.asarray(stamps, dtype=np.float64).reshape(-1)
        n = times.size
        up: tuple[FloatArray, FloatArray] = (np.zeros((n, 3)), np.tile(IDENTITY_QUATERNION, (n, 1)))
        down = (up[0].copy(), up[1].copy())
        for child, from_source in self._path(target, source):
            edge = self._edge_at(child, times, target, source)
            if from_source:
                up = compose(edge, up)
            else:
                down = compose(edge, down)
        return compose(invert(down), up)

    def lookup_matrix(self, target: str, source: str, stamp: float) -> FloatArray:
        """``T_target_source`` at one stamp as a 4x4 homogeneous matrix."""
        t, q = self.lookup(target, source, [stamp])
        out = np.eye(4)
        out[:3, :3] = quaternion_to_matrix(q[0])
        out[:3, 3] = t[0]
        return out

    def _path(self, target: str, source: str) -> list[tuple[str, bool]]:
        """Edges (child, on the source side) from both frames to their common ancestor."""
        target, source = normalize_frame(target), normalize_frame(source)
        if target == source:
            return []
        from_source, from_target = self.ancestors(source), self.ancestors(target)
        common = next((f for f in from_source if f in set(from_target)), None)
        if common is None:
            known = ", ".join(sorted(self.frames())) or "none"
            raise TransformUnavailable(
                "unconnected",
                f"no TF chain from {source!r} to {target!r} (frames known: {known})",
            )
        up = from_source[: from_source.index(common)]
        down = from_target[: from_target.index(common)]
        return [(c, True) for c in up] + [(c, False) for c in down]

    def _edge_at(
        self, child: str, times: FloatArray, target: str, source: str
    ) -> tuple[FloatArray, FloatArray]:
        n = times.size
        if child not in self._dynamic:
            _, t, q = self._static[child]
            return np.broadcast_to(t, (n, 3)), np.broadcast_to(q, (n, 4))
        edge = self._dynamic[child]
        what = f"{target} <- {source}: edge {edge.parent} -> {child}"
        stamps, translations, quaternions = edge.arrays()
        return interpolate_samples(
            stamps,
            translations,
            quaternions,
            times,
            self.max_gap,
            what=f"{what}: ",
            noun="transform",
            error=TransformUnavailable,
        )


class TfChain:
    """``T_target_source`` of a tree as a pose source: ``interpolate`` like a PoseBuffer."""

    def __init__(self, tree: TfTree, target: str, source: str) -> None:
        self.tree, self.target, self.source = tree, target, source

    @property
    def latest_stamp(self) -> float | None:
        """Latest stamp the chain covers; +inf when it is static only; None when broken."""
        try:
            latest = self.tree.latest_common_stamp(self.target, self.source)
        except TransformUnavailable:
            return None
        return math.inf if latest is None else latest

    def interpolate_quaternions(self, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]:
        return self.tree.lookup(self.target, self.source, stamps)

    def interpolate(self, stamps: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Positions (N, 3) and rotation matrices (N, 3, 3); raises TransformUnavailable."""
        t, q = self.interpolate_quaternions(stamps)
        return t, quaternion_to_matrix(q)


def normalize_frame(frame: str) -> str:
    """Frame id without tf1's leading slash."""
    return str(frame).lstrip("/")
