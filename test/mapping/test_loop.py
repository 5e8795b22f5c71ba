"""The one loop (``mapping.loop``): the same cloud gets the same fate in the live worker and the
replay."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mfp_mapper.config.sections import PlacementSection
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapping import loop
from mfp_mapper.sensing import pipeline
from mfp_mapper.sensing.poses import Extrinsic, PoseBuffer
from mfp_mapper.sources.scan_files import cloud_message_from_columns

T0 = 1000.0


def _cloud(n: int = 50, stamp: float = T0, **extra: np.ndarray) -> object:
    rng = np.random.default_rng(1)
    xyz = rng.uniform(1.0, 5.0, (n, 3)).astype(np.float32)
    return cloud_message_from_columns(
        {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], **extra}, stamp
    )


def _poses(*stamps: float) -> PoseBuffer:
    buffer = PoseBuffer(max_age=100.0, max_gap=0.5)
    for t in stamps:
        buffer.add(t, [t - T0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    return buffer


def _run(msg: object, poses: PoseBuffer, settings: PlacementSection | None = None) -> str:
    """The pipeline's verdict on one message: "integrated" or the drop reason."""
    mapper = Mapper(0.2)
    try:
        cloud = pipeline.parse_scan(msg)
        stamp = pipeline.scan_stamp(msg)
        placed = pipeline.place_scan(
            cloud, stamp, poses, Extrinsic(), settings or PlacementSection()
        )
        loop.integrate_scan(mapper, placed)
    except pipeline.ScanDropped as drop:
        assert drop.reason in pipeline.DROP_REASONS
        return drop.reason
    return "integrated"


def test_reasons_of_the_pipeline() -> None:
    poses = _poses(T0 - 0.2, T0, T0 + 0.2)
    assert _run(_cloud(), poses) == "integrated"
    assert _run(cloud_message_from_columns({"x": np.ones(3, np.float32)}), poses) == "malformed"
    nan = {a: np.full(4, np.nan, np.float32) for a in "xyz"}
    assert _run(cloud_message_from_columns(nan, T0), poses) == "empty"
    assert _run(_cloud(stamp=T0 + 5.0), poses) == "too_new"
    assert _run(_cloud(stamp=T0 - 5.0), poses) == "too_old"
    assert _run(_cloud(), PoseBuffer()) == "no_poses"
    assert _run(_cloud(stamp=T0 + 0.5), _poses(T0, T0 + 1.0)) == "gap"
    band = PlacementSection(point_cloud_min_z=10.0, point_cloud_max_z=11.0)
    assert _run(_cloud(), poses, band) == "empty"
    assert _run(_cloud(), poses, PlacementSection(point_cloud_max_x=0.5)) == "empty"  # x/y too
    assert _run(_cloud(), poses, PlacementSection(point_cloud_min_y=6.0)) == "empty"


def test_deskew_needs_poses_up_to_the_last_point() -> None:
    times = np.linspace(0.0, 0.1, 50).astype(np.float32)
    msg = _cloud(time=times)
    cloud = pipeline.parse_scan(msg)
    assert pipeline.pose_deadline(cloud, T0, deskew=True) == pytest.approx(T0 + 0.1, abs=1e-6)
    assert pipeline.pose_deadline(cloud, T0, deskew=False) == T0
    assert _run(msg, _poses(T0 - 0.1, T0 + 0.05)) == "too_new"
    assert _run(msg, _poses(T0 - 0.1, T0 + 0.05), PlacementSection(deskew=False)) == "integrated"


def test_a_cloud_the_core_cannot_use_is_dropped_not_integrated() -> None:
    # a sensor beyond the index range around the map's origin (a ray merely longer than
    # the core's walk limit is walked that far, with no return: used, not dropped)
    mapper = Mapper(0.1, max_range=math.inf, origin=(0.0, 0.0, 0.0))
    far = np.full((5, 3), 1e9)
    far[:, 0] += 1.0
    placed = pipeline.PlacedScan(T0, far, np.full(3, 1e9), False)
    version = mapper.version
    with pytest.raises(pipeline.ScanDropped) as info:
        loop.integrate_scan(mapper, placed)
    assert info.value.reason == "no_usable_rays"
    assert mapper.num_voxels == 0 and mapper.version == version


def test_counts_of_a_dropped_empty_cloud_keep_its_points() -> None:
    counts = loop.ScanCounts()
    nan = {a: np.full(7, np.nan, np.float32) for a in "xyz"}
    with pytest.raises(pipeline.ScanDropped) as info:
        pipeline.parse_scan(cloud_message_from_columns(nan, T0))
    counts.dropped_scan(info.value)
    assert counts.clouds_dropped == {"empty": 1}
    assert counts.points_in == 7 and counts.points_dropped == {"nonfinite": 7}


def test_unknown_reasons_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown drop reason"):
        pipeline.ScanDropped("bad_cloud", "old vocabulary")


def test_intensities_go_through_the_loop_into_the_histograms() -> None:
    """A cloud's ``reflectivity`` (Ouster) wins over its ``intensity``; points left out by the
    height band take their intensity with them; the map keeps its first field, a cloud of
    another field is integrated without histograms; ``reflectivity_bins`` 0 keeps none."""
    n = 50
    ouster = _cloud(
        n, reflectivity=np.full(n, 100.0, np.float32), intensity=np.full(n, 3.0, np.float32)
    )
    velodyne = _cloud(n, T0 + 0.2, intensity=np.arange(n, dtype=np.float32))
    cloud = pipeline.parse_scan(ouster)
    assert cloud.intensity_field == "reflectivity" and np.all(cloud.intensity == 100.0)
    band = PlacementSection(point_cloud_max_z=3.0)
    mapper = Mapper(0.2)
    kept = []
    for msg in (ouster, velodyne):
        parsed = pipeline.parse_scan(msg)
        placed = pipeline.place_scan(
            parsed, pipeline.scan_stamp(msg), _poses(T0, T0 + 0.2), Extrinsic(), band
        )
        assert placed.intensity is not None and len(placed.intensity) == len(placed.points)
        kept.append(len(placed.points))
        loop.integrate_scan(mapper, placed)
        if msg is velodyne:
            assert loop.scan_reflectivity(mapper, placed) is None  # another field
    table = mapper.stored_reflectivity()
    assert table is not None and table.bins.field == "reflectivity"
    assert table.counts[:, 6].sum() == table.counts.sum()  # 100 is in [64, 128)
    assert table.counts.sum() == kept[0] < n  # every return of the band, the Ouster cloud's
    off = Mapper(0.2, reflectivity_bins=0)
    loop.integrate_scan(off, placed)
    assert off.stored_reflectivity() is None
    assert pipeline.parse_scan(_cloud(n)).intensity_field is None
