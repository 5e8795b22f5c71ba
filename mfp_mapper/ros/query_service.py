"""``~/query`` (``mfp_mapper_msgs/srv/QueryMap``): what the map says at points and along
straight segments, answered as a service.

The work runs off the executor (``GuardedNode.off_executor``) and holds the map lock only
while it reads (the worker holds it only to merge a scan), so the service answers while
scans integrate and never blocks the executor. A request the node cannot answer (a
non-finite point, more points or segments than the limits, a segment longer than the limit,
a frame TF cannot transform) gets ``success: false`` and a message, never silence.
"""

from __future__ import annotations

import array
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.config.frames import frame_name
from mfp_mapper.config.sections import QuerySection
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.core.reflectivity import ReflectivityBins, mean_value
from mfp_mapper.sensing.tf_tree import TransformUnavailable

FloatArray = NDArray[np.float64]


class QueryRefused(ValueError):
    """A request outside what the service answers; the message says why."""


def points_array(points: Any) -> FloatArray:
    """``geometry_msgs/Point[]`` as an (N, 3) float64 array."""
    out = np.empty((len(points), 3))
    for k, p in enumerate(points):
        out[k] = (p.x, p.y, p.z)
    return out


def flat_array(values: Any, per: int, name: str) -> FloatArray:
    """A flat float64[] field as (N, ``per``); QueryRefused when its length does not divide."""
    flat = np.asarray(values, dtype=np.float64)
    if flat.size % per:
        raise QueryRefused(f"{name} holds {flat.size} numbers: not a multiple of {per}")
    return flat.reshape(-1, per)


def stamp_of(stamp: Any) -> float | None:
    """Seconds of a builtin_interfaces/Time; None for zero ("the latest")."""
    if stamp.sec == 0 and stamp.nanosec == 0:
        return None
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def check_request(
    points: FloatArray, starts: FloatArray, ends: FloatArray, limits: QuerySection
) -> None:
    """QueryRefused unless the request is within ``limits`` and finite."""
    if len(starts) != len(ends):
        raise QueryRefused(
            f"{len(starts)} segment_starts but {len(ends)} segment_ends: they go in pairs"
        )
    if len(points) > limits.max_points:
        raise QueryRefused(
            f"{len(points)} points: at most {limits.max_points} a request (query.max_points)"
        )
    if len(starts) > limits.max_segments:
        raise QueryRefused(
            f"{len(starts)} segments: at most {limits.max_segments} a request (query.max_segments)"
        )
    for name, values in (("points", points), ("segment_starts", starts), ("segment_ends", ends)):
        bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
        if bad.size:
            raise QueryRefused(f"{name}[{int(bad[0])}] is not finite: {values[bad[0]].tolist()}")
    if len(starts):
        lengths = np.linalg.norm(ends - starts, axis=1)
        longest = int(np.argmax(lengths))
        if lengths[longest] > limits.max_segment_length:
            raise QueryRefused(
                f"segment {longest} is {lengths[longest]:.6g} m long: at most "
                f"{limits.max_segment_length:g} m (query.max_segment_length)"
            )


@dataclass
class QueryResult:
    """The answers, in the map frame's terms."""

    hit_probability: FloatArray
    degree_of_occupancy: FloatArray
    std: FloatArray
    mean_free_path: FloatArray
    observed: NDArray[np.bool_]
    segment_clear_probability: FloatArray
    segment_unknown_length: FloatArray
    reflectivity: tuple[ReflectivityBins, FloatArray] | None = None
    """The bins and each point's reflectivity histogram (M, J), when the map keeps them."""


def answer(
    mapper: Mapper,
    lock: threading.Lock,
    points: FloatArray,
    starts: FloatArray,
    ends: FloatArray,
    stamp: float | None,
) -> QueryResult:
    """Read the map under ``lock`` (points and segments already in the map frame). A
    never-observed voxel has every estimate NaN (hit probability, DoO, std, mean free path):
    unknown, not free (its prior's hit probability, 0.012 at 0.1 m with the default prior,
    would read as free space)."""
    with lock:
        stats = mapper.query(points, stamp)
        segments = mapper.query_segments(starts, ends, stamp)
        reflectivity = mapper.reflectivity(points, stamp)
    unseen = ~stats.observed
    hit, doo, std, mfp = (
        np.where(unseen, math.nan, v)
        for v in (stats.hit_probability, stats.most_likely_doo, stats.std, stats.mean_free_path)
    )
    return QueryResult(
        hit, doo, std, mfp, stats.observed, segments.clear_probability, segments.unknown_length,
        reflectivity,
    )  # fmt: skip


def _doubles(values: FloatArray) -> array.array[float]:
    """A float64[] field's value that rclpy takes without a per-element check (a list of
    10,000 floats took 2 ms a field)."""
    return array.array("d", np.ascontiguousarray(values, dtype=np.float64).tobytes())


def fill_response(response: Any, result: QueryResult, map_frame: str, message: str) -> Any:
    """``response`` (QueryMap.Response) with ``result``."""
    response.success = True
    response.message = message
    response.map_frame_id = map_frame
    response.hit_probability = _doubles(result.hit_probability)
    response.degree_of_occupancy = _doubles(result.degree_of_occupancy)
    response.std = _doubles(result.std)
    response.mean_free_path = _doubles(result.mean_free_path)
    response.observed = result.observed.tolist()
    response.segment_clear_probability = _doubles(result.segment_clear_probability)
    response.segment_unknown_length = _doubles(result.segment_unknown_length)
    if result.reflectivity is not None:
        bins, counts = result.reflectivity
        response.reflectivity_counts = _doubles(counts.reshape(-1))
        response.reflectivity_mean = _doubles(mean_value(counts, bins))
        response.reflectivity_field = bins.field
        response.reflectivity_edges = _doubles(np.asarray(bins.edges, dtype=np.float64))
    return response


def refuse(response: Any, map_frame: str, message: str) -> Any:
    """``response`` saying why nothing was answered (empty arrays)."""
    response.success = False
    response.message = message
    response.map_frame_id = map_frame
    return response


class QueryService:
    """Serves ``~/query`` for a node: ``map_access`` gives the Mapper and its lock,
    ``to_map_frame(points, frame, stamp)`` transforms (raising ``TransformUnavailable``),
    ``map_frame()`` names the map frame, ``limits()`` the current ``query.*`` section."""

    def __init__(
        self,
        node: Any,
        map_access: Callable[[], tuple[Mapper, threading.Lock]],
        to_map_frame: Callable[[FloatArray, str, float], FloatArray],
        map_frame: Callable[[], str],
        limits: Callable[[], QuerySection],
    ) -> None:
        self._node = node
        self._map_access = map_access
        self._to_map_frame = to_map_frame
        self._map_frame = map_frame
        self._limits = limits
        self.answered = 0
        self.refused = 0

    async def on_request(self, request: Any, response: Any) -> Any:
        """The service callback (wrap it with ``tracked``)."""
        frame = self._map_frame()
        try:
            bulk = flat_array(request.segments_xyz, 6, "segments_xyz")
            points = np.vstack(
                [points_array(request.points), flat_array(request.points_xyz, 3, "points_xyz")]
            )
            starts = np.vstack([points_array(request.segment_starts), bulk[:, :3]])
            ends = np.vstack([points_array(request.segment_ends), bulk[:, 3:]])
            check_request(points, starts, ends, self._limits())
            stamp = stamp_of(request.stamp)
            given = frame_name(request.frame_id.strip())
            if given and given != frame:
                when = stamp if stamp is not None else 0.0
                moved = self._to_map_frame(np.vstack([points, starts, ends]), given, when)
                k, s = len(points), len(starts)
                points, starts, ends = moved[:k], moved[k : k + s], moved[k + s :]
            mapper, lock = self._map_access()
            result = await self._node.off_executor(
                lambda: answer(mapper, lock, points, starts, ends, stamp)
            )
        except QueryRefused as err:
            self.refused += 1
            return refuse(response, frame, str(err))
        except TransformUnavailable as err:
            self.refused += 1
            return refuse(
                response, frame, f"frame {request.frame_id!r} cannot be transformed into the "
                f"map frame {frame!r}: {err}",
            )  # fmt: skip
        except ValueError as err:  # the walk refuses a segment (beyond the map's index range)
            self.refused += 1
            return refuse(response, frame, str(err))
        self.answered += 1
        message = f"{len(points)} points, {len(starts)} segments"
        return fill_response(response, result, frame, message)
