"""The project's own TF buffer (no tf2_ros), with tf2's semantics: static and dynamic
transforms, chain lookups, expiry, one parent per frame.

Frames form a tree: each child frame has one parent at a time. Static edges
(``/tf_static``) hold one transform for all time; dynamic edges (``/tf``) hold the samples
of the last ``buffer_length`` seconds (tf2's cache time, 10 s by default), interpolated at
lookup (translation linear, rotation slerp). A lookup of ``target <- source`` walks both
frames up to their common ancestor and composes the edges at each requested stamp, so a
whole scan is looked up at once for de-skew.

What tf2 does, and this buffer too:

- **Expiry**: a dynamic edge whose latest sample is more than ``buffer_length`` seconds
  older than the newest sample of the stream is forgotten (its frame too, when nothing
  else names it): a stray message stops mattering after the cache time, and churned frame
  names do not accumulate. A static edge shadowed by a dynamic one comes back then.
- **One parent per frame**: a message giving a frame another parent replaces its edge,
  with one event naming both parents; the replaced samples are kept aside, so a single
  stray costs nothing once the usual parent speaks again, and a new parent is not used
  before a second message confirms it (one stray message never places a cloud). A frame
  whose parent changes ``CONFLICT_CHANGES`` times within the cache time is in *conflict*
  (two localizers publishing it): lookups through it fail naming both parents until it
  settles.
- **Loops are refused**: a message whose child is an ancestor of its parent is never
  stored (``rejected["loop"]``, an event names the frames).
- **Stamps**: a sample more than ``max_jump`` seconds away from the stream's newest (ahead
  *or behind*) is held back until a second one confirms the jump; a confirmed jump clears
  the dynamic edges and the stream goes on from there (as odometry does; tf2 clears on a
  clock jump back). With a reference clock (``now``) a sample more than ``max_future``
  seconds ahead of it is refused. :meth:`TfTree.observe_clock` clears the dynamic edges
  when the clock jumps back.

Events (:meth:`TfTree.take_events`) are ``(kind, text)`` pairs for the caller's throttled
log; ``kind`` never holds a frame name, and every text names at most a handful of frames.
Vectors are rotated with scipy's ``Rotation``; only the quaternion product is ours
(``quaternion_multiply`` says why). Quaternions are ``(x, y, z, w)``;
``T_a_b`` maps points in ``b`` into ``a``.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import Counter, deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from mfp_mapper.config.frames import frame_name
from mfp_mapper.sensing.pointcloud import stamp_seconds
from mfp_mapper.sensing.poses import (
    IDENTITY_QUATERNION,
    PoseUnavailable,
    interpolate_samples,
    quaternion_to_matrix,
)

FloatArray = NDArray[np.float64]
Transform = tuple[FloatArray, FloatArray]
TransformRecord = tuple[str, str, float, float, float, float, float, float, float, float]
"""One transform as plain values: (parent, child, stamp s, x, y, z, qx, qy, qz, qw)."""
_MAX_DEPTH = 64
CONFLICT_CHANGES = 3
"""Parent changes of one frame within the cache time that make it a conflict (a single
stray message makes two: away and back)."""
NAMES_SHOWN = 5
"""Frames an error line names at most."""


def frame_list(names: Iterable[str], limit: int = NAMES_SHOWN) -> str:
    """``'a', 'b', 'c' and 7 more``: at most ``limit`` names, sorted."""
    ordered = sorted(names)
    shown = ", ".join(repr(n) for n in ordered[:limit]) or "none"
    return shown + (f" and {len(ordered) - limit} more" if len(ordered) > limit else "")


def _unit_quaternion(q: ArrayLike) -> FloatArray | None:
    """One quaternion normalised (plain floats: a TF message at a time); None if invalid."""
    try:
        x, y, z, w = (float(v) for v in np.asarray(q, dtype=np.float64).reshape(-1))
    except (TypeError, ValueError):
        return None
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not (math.isfinite(norm) and norm > 1e-12):
        return None
    return np.array([x / norm, y / norm, z / norm, w / norm])


def transform_records(msg: Any) -> list[TransformRecord]:
    """The transforms of a tf2_msgs/TFMessage (rclpy or rosbags) as plain values."""
    out: list[TransformRecord] = []
    for tf in msg.transforms:
        tr, rot = tf.transform.translation, tf.transform.rotation
        out.append((str(tf.header.frame_id), str(tf.child_frame_id),
                    stamp_seconds(tf.header.stamp), tr.x, tr.y, tr.z,
                    rot.x, rot.y, rot.z, rot.w))  # fmt: skip
    return out


class TransformUnavailable(PoseUnavailable):
    """No transform for a lookup. Reasons: those of PoseUnavailable (``"no_poses"``,
    ``"too_new"``, ``"too_old"``, ``"gap"``, each naming the edge), ``"unconnected"``
    (no chain between the frames, or an unknown frame) and ``"tf_conflict"`` (a frame of
    the chain has two parents alternately)."""


def quaternion_multiply(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product ``a * b`` (xyzw, broadcast): rotate by ``b`` then by ``a``.

    Hand-written because scipy's ``Rotation.__mul__`` is the one slow step of a chain
    lookup, and a de-skewed scan composes several edges at every point time: for 10k
    rotations (scipy 1.17, same process, 3 interleaved runs) 32-48 ms against 1-2 ms here;
    ``compose`` with ``Rotation`` throughout took 43-51 ms against 4-5 ms with this
    product (``Rotation.apply`` for the translation costs 0.6 ms). Checked against
    scipy's rotation matrices in the tests.
    """
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


def compose(outer: Transform, inner: Transform) -> Transform:
    """``T_a_c`` from ``T_a_b`` (outer) and ``T_b_c`` (inner), as (translation, quaternion);
    broadcast over a leading axis of N transforms."""
    t_ab, q_ab = outer
    t_bc, q_bc = inner
    if np.size(q_ab) == 0 or np.size(q_bc) == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    return Rotation.from_quat(q_ab).apply(t_bc) + t_ab, quaternion_multiply(q_ab, q_bc)


def invert(transform: Transform) -> Transform:
    """``T_b_a`` from ``T_a_b``."""
    t, q = transform
    if np.size(q) == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    inverse = Rotation.from_quat(q).inv()
    return -inverse.apply(t), inverse.as_quat()


@dataclass(slots=True)
class _Edge:
    """Samples of one dynamic edge (child in parent), sorted by stamp."""

    parent: str
    stamps: list[float] = field(default_factory=list)
    translations: list[tuple[float, float, float]] = field(default_factory=list)
    quaternions: list[tuple[float, float, float, float]] = field(default_factory=list)
    _arrays: tuple[FloatArray, FloatArray, FloatArray] | None = None

    def insert(
        self,
        stamp: float,
        t: tuple[float, float, float],
        q: tuple[float, float, float, float],
        buffer_length: float,
    ) -> None:
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

    def copy(self) -> _Edge:
        return _Edge(
            self.parent,
            list(self.stamps),
            list(self.translations),
            list(self.quaternions),
            self._arrays,
        )

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


@dataclass(slots=True)
class _Frame:
    """The dynamic side of one child frame: its edge, the edge it replaced, and when its
    parent changed (stream time)."""

    edge: _Edge
    previous: _Edge | None = None
    changes: list[float] = field(default_factory=list)
    pending: float | None = None

    def copy(self) -> _Frame:
        return _Frame(
            self.edge.copy(),
            None if self.previous is None else self.previous.copy(),
            list(self.changes),
        )


class TfTree:
    """Static and dynamic transforms, looked up as chains at one or many stamps (the
    module docstring says what is stored and what is refused)."""

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
        """Samples not stored, by reason: invalid, loop, old (behind its edge's cache),
        future_outlier, past_outlier (a jump not confirmed yet), ahead_of_clock."""
        self.stripped_slash = 0
        """Frame names given with tf1's leading slash (stripped)."""
        self._static: dict[str, tuple[str, FloatArray, FloatArray]] = {}
        self._dynamic: dict[str, _Frame] = {}
        self._newest: float | None = None
        self.pending: float | None = None
        """A far-off stamp of a new edge waiting for confirmation (see ``_plausible``)."""
        self._pruned_at = -math.inf
        self._peak = 0
        self._last_clock: float | None = None
        self._events: deque[tuple[str, str]] = deque(maxlen=16)

    # --- input ---------------------------------------------------------------------------

    def add_message(self, msg: Any, static: bool, now: float | None = None) -> int:
        """Add every transform of a tf2_msgs/TFMessage (rclpy or rosbags); how many stored."""
        return self.add_records(transform_records(msg), static, now)

    def add_records(
        self, records: Iterable[TransformRecord], static: bool, now: float | None = None
    ) -> int:
        """Add transforms given as plain values (``TransformRecord``); how many stored.

        The per-transform path of a TF flood (10,000 frames a second): plain floats, no
        numpy per transform, the pruning once per message. Inserting 100 new frames beside
        60,000 took 1.28 CPU ms a message with the numpy-checked ``add`` of before and
        0.46 ms here (same process, garbage collector off; ``benchmarks/bench_tf_flood.py``
        times the node's whole path)."""
        stored = 0
        for parent, child, stamp, tx, ty, tz, qx, qy, qz, qw in records:
            stored += self._add_values(parent, child, stamp, (tx, ty, tz), (qx, qy, qz, qw),
                                       static, now)  # fmt: skip
        self._maybe_prune()
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
        t = np.asarray(translation, dtype=np.float64).reshape(-1)
        q = _unit_quaternion(quaternion_xyzw)
        if q is None or t.shape != (3,):
            self.rejected["invalid"] += 1
            return False
        stored = self._add_values(
            parent, child, stamp, (float(t[0]), float(t[1]), float(t[2])),
            (float(q[0]), float(q[1]), float(q[2]), float(q[3])), static, now,
        )  # fmt: skip
        self._maybe_prune()
        return stored

    def _add_values(
        self,
        parent: str,
        child: str,
        stamp: float,
        t: tuple[float, float, float],
        q: tuple[float, float, float, float],
        static: bool,
        now: float | None,
    ) -> bool:
        """``add`` on plain floats (pruning left to the caller)."""
        parent, child = self._name(parent), self._name(child)
        try:
            qx, qy, qz, qw = float(q[0]), float(q[1]), float(q[2]), float(q[3])
            tx, ty, tz = float(t[0]), float(t[1]), float(t[2])
            stamp = float(stamp)
            norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        except (TypeError, ValueError, OverflowError):
            self.rejected["invalid"] += 1
            return False
        if not (
            math.isfinite(norm)
            and norm > 1e-12
            and math.isfinite(tx)
            and math.isfinite(ty)
            and math.isfinite(tz)
            and math.isfinite(stamp)
        ):
            self.rejected["invalid"] += 1
            return False
        translation = (tx, ty, tz)
        rotation = (qx / norm, qy / norm, qz / norm, qw / norm)
        if not parent or not child or parent == child:
            self.rejected["invalid"] += 1
            return False
        if self._closes_loop(parent, child):
            self.rejected["loop"] += 1
            self._event(
                "tf_loop",
                f"transform {parent!r} -> {child!r} refused: {child!r} is already above "
                f"{parent!r} (it would close a loop; {self.rejected['loop']} refused so far)",
            )
            return False
        if static:
            return self._add_static(parent, child, np.array(translation), np.array(rotation))
        if now is not None and stamp > now + self.max_future:
            self.rejected["ahead_of_clock"] += 1
            return False
        return self._add_dynamic(parent, child, stamp, translation, rotation)

    def _name(self, frame: str) -> str:
        name = frame if type(frame) is str else str(frame)
        if name.startswith("/"):
            self.stripped_slash += 1
            if self.stripped_slash == 1:
                self._event(
                    "tf_slash",
                    f"frame {name!r} has a leading slash: read as {frame_name(name)!r} "
                    "(tf2 rejects such names; fix the publisher)",
                )
            return frame_name(name)
        return name

    def _closes_loop(self, parent: str, child: str) -> bool:
        frame: str | None = parent
        for _ in range(_MAX_DEPTH):
            if frame is None:
                return False
            if frame == child:
                return True
            dynamic = self._dynamic.get(frame)  # names are stripped already: no parent()
            if dynamic is not None:
                frame = dynamic.edge.parent
            else:
                static = self._static.get(frame)
                frame = None if static is None else static[0]
        return True

    def _add_static(self, parent: str, child: str, t: FloatArray, q: FloatArray) -> bool:
        old = self._static.get(child)
        if old is not None and old[0] != parent:
            self._event(
                "tf_parent",
                f"static transform gives frame {child!r} the parent {parent!r} instead of "
                f"{old[0]!r}: replaced",
            )
        self._static[child] = (parent, t, q)
        self._dynamic.pop(child, None)
        return True

    def _add_dynamic(
        self,
        parent: str,
        child: str,
        stamp: float,
        t: tuple[float, float, float],
        q: tuple[float, float, float, float],
    ) -> bool:
        frame = self._dynamic.get(child)
        if not self._plausible(frame, stamp):
            return False
        if frame is None:
            static = self._static.get(child)
            frame = self._dynamic[child] = _Frame(_Edge(parent))
            if static is not None and static[0] != parent:
                frame.changes.append(stamp)
                self._event(
                    "tf_parent",
                    f"/tf gives frame {child!r} the parent {parent!r} while /tf_static gives "
                    f"{static[0]!r}: {parent!r} is used until its transforms stop for "
                    f"{self.buffer_length:g} s",
                )
        elif frame.edge.parent != parent:
            self._change_parent(frame, child, parent, stamp)
        frame.edge.insert(stamp, t, q, self.buffer_length)
        if self._newest is None or stamp > self._newest:
            self._newest = stamp
        return True

    def _change_parent(self, frame: _Frame, child: str, parent: str, stamp: float) -> None:
        old = frame.edge.parent
        keep = frame.previous
        frame.previous = frame.edge
        frame.edge = keep if keep is not None and keep.parent == parent else _Edge(parent)
        frame.changes = [s for s in frame.changes if s > stamp - self.buffer_length] + [stamp]
        if len(frame.changes) >= CONFLICT_CHANGES:
            self._event(
                "tf_conflict",
                f"frame {child!r} gets its parent alternately from {old!r} and {parent!r} "
                f"({len(frame.changes)} changes in {self.buffer_length:g} s): two nodes "
                "publish it (two localizers?); lookups through it fail until one stops",
            )
        else:
            self._event(
                "tf_parent",
                f"frame {child!r} gets the parent {parent!r} instead of {old!r} "
                "(one parent per frame: the edge is replaced)",
            )

    def _plausible(self, frame: _Frame | None, stamp: float) -> bool:
        """The stamp check of odometry's ``StampGuard``, per edge: a stamp more than
        ``max_jump`` from its edge's latest (a new edge: from the stream's newest), ahead or
        behind, needs a second one to confirm the jump; then that edge starts over (and the
        stream's newest follows a jump back of the leading edges)."""
        edge_latest = frame.edge.stamps[-1] if frame is not None else None
        ref = edge_latest if edge_latest is not None else self._newest
        holder = frame if frame is not None else self
        if ref is None or abs(stamp - ref) <= self.max_jump:
            holder.pending = None
            if edge_latest is not None and stamp < edge_latest - self.buffer_length:
                self.rejected["old"] += 1
                return False
            return True
        pending = holder.pending
        if pending is None or abs(stamp - pending) > self.max_jump:
            holder.pending = stamp
            self.rejected["future_outlier" if stamp > ref else "past_outlier"] += 1
            return False
        holder.pending = None
        self._event(
            "tf_jump",
            f"TF stamps jumped {'back' if stamp < ref else 'ahead'} {abs(stamp - ref):.3f} s "
            f"(to {stamp:.3f}; confirmed by a second message): that transform starts over",
        )
        if frame is not None:
            frame.edge = _Edge(frame.edge.parent)
            frame.previous = None
        leading = self._newest is None or ref >= self._newest - self.max_jump
        if stamp < ref and leading:
            self._newest = stamp
        return True

    def _maybe_prune(self) -> None:
        """Forget the edges the stream left behind (at most every tenth of the cache time,
        or when the frame count doubled: amortised O(1) per sample)."""
        newest = self._newest
        if newest is None or not math.isfinite(self.buffer_length):
            return
        if newest - self._pruned_at < 0.1 * self.buffer_length and len(self._dynamic) < max(
            2 * self._peak, 64
        ):
            return
        self._pruned_at = newest
        cut = newest - self.buffer_length
        stale = [c for c, f in self._dynamic.items() if f.edge.stamps[-1] < cut]
        for child in stale:
            del self._dynamic[child]
        for frame in self._dynamic.values():
            if frame.previous is not None and frame.previous.stamps[-1] < cut:
                frame.previous = None
            if frame.changes and frame.changes[0] < cut:
                frame.changes = [s for s in frame.changes if s >= cut]
        if len(stale) > len(self._dynamic):
            self._dynamic = dict(self._dynamic)  # a dict never shrinks its table by itself
        self._peak = len(self._dynamic)

    def take_events(self) -> list[tuple[str, str]]:
        """``(kind, text)`` of what was replaced, refused or cleared since the last call."""
        events = list(self._events)
        self._events.clear()
        return events

    def _event(self, kind: str, text: str) -> None:
        self._events.append((kind, text))

    def snapshot(self, frames: Iterable[str] | None = None) -> TfTree:
        """A copy that later ``add`` calls leave unchanged (lookups outside a lock).

        ``frames``: only the edges on their chains up to their roots (what lookups between
        them need). Copying the whole tree took 300 ms under the lock with 20,000 frames (a
        TF flood): every cloud placed held up the executor's TF and the queue filled."""
        copy = TfTree(self.buffer_length, self.max_gap, self.max_jump, self.max_future)
        if frames is None:
            copy._static = dict(self._static)
            copy._dynamic = {child: f.copy() for child, f in self._dynamic.items()}
        else:
            chains = self._chains(frames)
            copy._static = {c: self._static[c] for c in chains if c in self._static}
            copy._dynamic = {c: self._dynamic[c].copy() for c in chains if c in self._dynamic}
        copy._newest = self._newest
        return copy

    def _chains(self, frames: Iterable[str]) -> set[str]:
        """``frames`` and every frame above them (static, dynamic and replaced parents)."""
        seen: set[str] = set()
        todo = [frame_name(f) for f in frames if f]
        while todo:
            frame = todo.pop()
            if frame in seen:
                continue
            seen.add(frame)
            if frame in self._static:
                todo.append(self._static[frame][0])
            dynamic = self._dynamic.get(frame)
            if dynamic is not None:
                todo.append(dynamic.edge.parent)
                if dynamic.previous is not None:
                    todo.append(dynamic.previous.parent)
        return seen

    def observe_clock(self, now: float) -> bool:
        """Note the reference clock; True (dynamic edges cleared) when it jumped back."""
        jumped = self._last_clock is not None and now < self._last_clock
        self._last_clock = now
        if jumped:
            self.clear()
        return jumped

    def clear(self, static: bool = False) -> None:
        """Forget the dynamic samples (and the static edges too with ``static``)."""
        self._dynamic = {}
        self._newest = self.pending = None
        self._pruned_at = -math.inf
        if static:
            self._static.clear()

    # --- structure -----------------------------------------------------------------------

    @property
    def newest_stamp(self) -> float | None:
        """Newest stamp of the dynamic stream (None before the first)."""
        return self._newest

    def frames(self) -> set[str]:
        """Every frame named by a stored edge."""
        names = set(self._static) | set(self._dynamic)
        names |= {p for p, _, _ in self._static.values()}
        return names | {f.edge.parent for f in self._dynamic.values()}

    def conflicts(self) -> dict[str, tuple[str, str]]:
        """Frames in conflict: child -> (its two alternating parents)."""
        out = {}
        for child, f in self._dynamic.items():
            if len(f.changes) >= CONFLICT_CHANGES and f.previous is not None:
                out[child] = (f.edge.parent, f.previous.parent)
        return out

    def parent(self, child: str) -> tuple[str, bool] | None:
        """The parent of ``child`` and whether the edge is static; None at a root."""
        child = frame_name(child)
        frame = self._dynamic.get(child)
        if frame is not None:
            return frame.edge.parent, False
        if child in self._static:
            return self._static[child][0], True
        return None

    def ancestors(self, frame: str) -> list[str]:
        """``frame`` then its parents up to its root."""
        chain = [frame_name(frame)]
        while (up := self.parent(chain[-1])) is not None:
            if up[0] in chain or len(chain) > _MAX_DEPTH:
                raise TransformUnavailable("unconnected", f"TF has a loop through {up[0]!r}")
            chain.append(up[0])
        return chain

    def static_chain(self, top: str, bottom: str) -> Transform | None:
        """``T_top_bottom`` through static edges only; None when they do not connect."""
        top, frame = frame_name(top), frame_name(bottom)
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
        frame = self._dynamic.get(frame_name(child))
        return np.array(frame.edge.stamps) if frame is not None else np.zeros(0)

    def is_dynamic(self, child: str) -> bool:
        """Whether the edge above ``child`` comes from /tf (moves)."""
        return frame_name(child) in self._dynamic

    def latest_common_stamp(self, target: str, source: str) -> float | None:
        """Latest stamp at which the chain can be looked up (None: static only or unknown)."""
        path = self._path(target, source)
        latest = [self._dynamic[c].edge.stamps[-1] for c, _ in path if c in self._dynamic]
        return min(latest) if latest else None

    # --- lookup --------------------------------------------------------------------------

    def lookup(self, target: str, source: str, stamps: ArrayLike) -> Transform:
        """``T_target_source`` at each stamp: translations (N, 3) and quaternions (N, 4).

        Raises TransformUnavailable naming the frames (and the edge that is missing)."""
        times = np.asarray(stamps, dtype=np.float64).reshape(-1)
        n = times.size
        up: Transform = (np.zeros((n, 3)), np.tile(IDENTITY_QUATERNION, (n, 1)))
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
        target, source = frame_name(target), frame_name(source)
        if target == source:
            return []
        from_source, from_target = self.ancestors(source), self.ancestors(target)
        common = next((f for f in from_source if f in set(from_target)), None)
        if common is None:
            raise TransformUnavailable(
                "unconnected",
                f"no TF chain from {source!r} (root {from_source[-1]!r}) to {target!r} "
                f"(root {from_target[-1]!r}); frames known: {frame_list(self.frames())}",
            )
        up = from_source[: from_source.index(common)]
        down = from_target[: from_target.index(common)]
        return [(c, True) for c in up] + [(c, False) for c in down]

    def _edge_at(self, child: str, times: FloatArray, target: str, source: str) -> Transform:
        n = times.size
        frame = self._dynamic.get(child)
        if frame is None:
            _, t, q = self._static[child]
            return np.broadcast_to(t, (n, 3)), np.broadcast_to(q, (n, 4))
        edge = frame.edge
        if len(frame.changes) >= CONFLICT_CHANGES and frame.previous is not None:
            raise TransformUnavailable(
                "tf_conflict",
                f"{target} <- {source}: frame {child!r} gets its parent alternately from "
                f"{edge.parent!r} and {frame.previous.parent!r} (two nodes publish it)",
            )
        if frame.changes and len(edge.stamps) < 2:
            raise TransformUnavailable(
                "too_new",
                f"{target} <- {source}: frame {child!r} got a new parent {edge.parent!r} in one "
                "message only: not used before a second one confirms it",
            )
        stamps, translations, quaternions = edge.arrays()
        return interpolate_samples(
            stamps,
            translations,
            quaternions,
            times,
            self.max_gap,
            what=f"{target} <- {source}: edge {edge.parent} -> {child}: ",
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
