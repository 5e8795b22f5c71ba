"""A Nav2 ``map_server`` map of a height band: ``NAME.pgm`` + ``NAME.yaml``.

The band ``[z_min, z_max]`` is projected exactly as the node's ``~/projected_map``
(``Mapper.hit_probability_grid(..., trinary=...)``, the same thresholds and defaults): per
cell ``p``, the largest hit probability (the probability that a ray crossing one voxel edge
is reflected, Eq. 31-34) among the observed voxels of the column. A cell is then

- occupied (pixel 0, OccupancyGrid 100) when ``p >= occupied_threshold``,
- free (pixel 254, OccupancyGrid 0) when ``p < free_threshold``,
- unknown (pixel 205, OccupancyGrid -1) otherwise, or when no voxel of the band was observed.

The YAML says ``mode: trinary``, ``negate: 0``, ``occupied_thresh: 0.65`` and
``free_thresh: 0.196``: map_server reads a pixel as ``occ = (255 - pixel) / 255`` and marks it
occupied when ``occ > occupied_thresh``, free when ``occ < free_thresh``: 0 -> 100, 254 -> 0,
205 (occ = 0.196078...) -> -1. The image's first row is the top (largest y) of the map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core.gridmap import DEFAULT_OCCUPIED_THRESHOLD, unobserved_hit_probability
from mfp_mapper.core.mapper import Mapper
from mfp_mapper.mapio.atomic import atomic_output, write_text_atomic

OCCUPIED_PIXEL, FREE_PIXEL, UNKNOWN_PIXEL = 0, 254, 205
MAP_SERVER_OCCUPIED_THRESH = 0.65
MAP_SERVER_FREE_THRESH = 0.196
MAP_SAVER_OCCUPIED_THRESH = 0.65
"""Nav2 map_saver_cli's default thresholds, for grids saved from a ``GetMap`` answer."""
MAP_SAVER_FREE_THRESH = 0.25


@dataclass
class Nav2Map:
    image: Path
    yaml: Path
    occupancy: NDArray[np.int8]
    """The OccupancyGrid values (100, 0, -1), row 0 = smallest y."""
    origin: tuple[float, float]
    resolution: float


def write_nav2_map(
    mapper: Mapper,
    path: str | Path,
    z_min: float,
    z_max: float,
    occupied_threshold: float | None = None,
    free_threshold: float | None = None,
) -> Nav2Map:
    """Write ``path`` (.yaml; the .pgm beside it) for the band ``[z_min, z_max]``.

    Thresholds default to the node's (``projected_map.occupied_threshold``; free: the hit
    probability of a never-observed voxel under the map's prior, ``1 - (rate / (rate +
    resolution))^shape``: 0.012 at 0.1 m with the default prior).
    """
    yaml_path = Path(path).with_suffix(".yaml")
    if occupied_threshold is None:
        occupied_threshold = DEFAULT_OCCUPIED_THRESHOLD
    if free_threshold is None or free_threshold < 0.0:
        unknown = unobserved_hit_probability(
            mapper.resolution, mapper.prior.shape, mapper.prior.rate
        )
        free_threshold = min(unknown, occupied_threshold)
    grid = mapper.hit_probability_grid(z_min, z_max, trinary=(occupied_threshold, free_threshold))
    if grid.data.size == 0:
        raise ValueError(f"no observed voxel in the band [{z_min}, {z_max}] m: no map")
    return _write_trinary(
        grid.data, grid.origin, grid.resolution, yaml_path, mapper.frame_id,
        f"band z in [{z_min}, {z_max}] m of {mapper.frame_id or 'map'}; hit probability "
        f">= {occupied_threshold} occupied, < {free_threshold:.6g} free",
    )  # fmt: skip


def write_occupancy_grid(
    values: Sequence[int] | NDArray[np.int8],
    shape: tuple[int, int],
    origin: tuple[float, float],
    resolution: float,
    path: str | Path,
    frame_id: str = "",
    occupied_thresh: float = MAP_SAVER_OCCUPIED_THRESH,
    free_thresh: float = MAP_SAVER_FREE_THRESH,
) -> Nav2Map:
    """Write an OccupancyGrid's cells (row-major, row 0 = smallest y; 0..100 or -1) as
    ``path`` (.yaml) and the .pgm beside it, as Nav2's ``map_saver_cli`` does in trinary
    mode: a cell >= ``occupied_thresh`` * 100 is occupied, <= ``free_thresh`` * 100 free, any
    other (and -1) unknown."""
    height, width = shape
    cells = np.asarray(values, dtype=np.int16).reshape(height, width)
    occupancy = np.full((height, width), -1, dtype=np.int8)
    occupancy[(cells >= 0) & (cells <= free_thresh * 100.0)] = 0
    occupancy[cells >= occupied_thresh * 100.0] = 100
    return _write_trinary(
        occupancy, origin, resolution, Path(path).with_suffix(".yaml"), frame_id,
        f"cells of frame {frame_id or 'map'}: >= {occupied_thresh:g} occupied, "
        f"<= {free_thresh:g} free (map_saver trinary)",
    )  # fmt: skip


def _write_trinary(
    occupancy: NDArray[np.int8],
    origin: tuple[float, float],
    resolution: float,
    yaml_path: Path,
    frame_id: str,
    comment: str,
) -> Nav2Map:
    """The .pgm (row 0 = the top, largest y) and .yaml of a trinary grid (100, 0, -1)."""
    image_path = yaml_path.with_suffix(".pgm")
    pixels: NDArray[np.uint8] = np.full(occupancy.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    pixels[occupancy == 100] = OCCUPIED_PIXEL
    pixels[occupancy == 0] = FREE_PIXEL
    height, width = occupancy.shape[0], occupancy.shape[1]
    with atomic_output(image_path) as f:
        f.write(f"P5\n# mfp_mapper {frame_id}\n{width} {height}\n255\n".encode("ascii"))
        f.write(np.flipud(pixels).tobytes())
    x0, y0 = origin
    text = (
        f"image: {image_path.name}\n"
        f"mode: trinary\n"
        f"resolution: {resolution!r}\n"
        f"origin: [{x0!r}, {y0!r}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {MAP_SERVER_OCCUPIED_THRESH}\n"
        f"free_thresh: {MAP_SERVER_FREE_THRESH}\n"
        f"# {comment}\n"
    )
    write_text_atomic(yaml_path, text)
    return Nav2Map(image_path, yaml_path, occupancy, (x0, y0), resolution)


def read_pgm(path: str | Path) -> NDArray[np.uint8]:
    """The pixels of a binary 8-bit PGM (P5), first row = top of the image."""
    raw = Path(path).read_bytes()
    tokens: list[bytes] = []
    position = 0
    while len(tokens) < 4:
        while raw[position : position + 1].isspace():
            position += 1
        if raw[position : position + 1] == b"#":
            position = raw.index(b"\n", position) + 1
            continue
        end = position
        while not raw[end : end + 1].isspace():
            end += 1
        tokens.append(raw[position:end])
        position = end
    if tokens[0] != b"P5" or int(tokens[3]) != 255:
        raise ValueError(f"{path}: not an 8-bit binary PGM")
    width, height = int(tokens[1]), int(tokens[2])
    body = raw[position + 1 : position + 1 + width * height]
    return np.frombuffer(body, dtype=np.uint8).reshape(height, width)
