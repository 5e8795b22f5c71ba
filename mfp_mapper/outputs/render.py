"""Pictures of a map (``mfp-mapper render``) and of the model (``plot-convergence``).

matplotlib with the Agg backend (no display needed). ``render_map`` writes

- ``doo_topdown.png``: per column the highest most likely (or posterior mean) degree of
  occupancy (DoO) in a height band; by default the band is found in the data: from 0.25 m above the
  floor, 2.25 m high, ending 0.25 m under a ceiling (floor and ceiling: the lowest and
  highest dense layers of the occupied-voxel height histogram); the view is cropped to the
  0.5-99.5 percentiles of the observed voxels, so a few outliers do not shrink the map;
- ``std_topdown.png``: the posterior std of the voxel drawn (largest DoO, ties to the most
  evidence, then the highest: no storage-order artefact);
- ``slice.png``: a vertical x-z slice at one y: most likely DoO and std;
- ``histogram.png``: histograms of the most likely DoO and of the std;
- ``reflectivity_topdown.png`` (a map with reflectivity histograms, docs/model.md): per column
  the mean intensity of the lowest voxel holding returns (the ground's: road markings,
  crosswalks), on a log colour scale, cropped like the top-down pictures.

Unobserved voxels are grey. ``plot_convergence`` writes ``convergence.png``: one cell
probed repeatedly (10 returns, then rays passing through), the degree of occupancy next to
the classic binary occupancy model, like Fig. 9 of Berquin & Zell (2021).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mfp_mapper.core import model
from mfp_mapper.core.mapper import Mapper, VoxelStats
from mfp_mapper.core.reflectivity import ReflectivityBins, mean_value

MAX_IMAGE_CELLS = 1600
"""Top-down and slice images are coarsened so that no side exceeds this many cells."""
STD_MAX = 0.5
"""Top of the colour scale of the std pictures: the largest standard deviation a DoO in
[0, 1] can have (the uniform prior's 0.2887 clipped the voxels of little evidence under a
small prior, such as the default's)."""


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


@dataclass
class RenderResult:
    files: list[Path] = field(default_factory=list)
    band: tuple[float, float] = (math.nan, math.nan)
    slice_y: float = math.nan
    extent: tuple[float, float, float, float] = (math.nan,) * 4
    """x min, x max, y min, y max of the top-down pictures (m, map frame)."""
    top_down: NDArray[np.float64] | None = None
    """The top-down DoO grid drawn ((x, y) cells, NaN unobserved)."""
    top_down_std: NDArray[np.float64] | None = None
    reflectivity: NDArray[np.float64] | None = None
    """The reflectivity grid drawn ((x, y) cells, NaN where no voxel holds returns)."""


BAND_HEIGHT = 2.25
"""Default height of the top-down band, from 0.25 m above the floor."""
DENSE_LAYER = 0.3
"""A horizontal layer holding at least this share of the fullest layer's occupied voxels
is a floor or a ceiling."""
CROP_PERCENTILES = (0.5, 99.5)
"""The top-down view spans these percentiles of the observed voxels' x and y (outliers
beyond are left out), plus a margin."""


def _occupied_layers(stats: VoxelStats) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    occ = stats.observed & (stats.most_likely_doo > 0.5) & (stats.n >= 1)
    values, counts = np.unique(stats.ijk[occ, 2], return_counts=True)
    return values.astype(np.int64), counts.astype(np.int64)


def _dense_surface(values: NDArray[np.int64], counts: NDArray[np.int64], k: int, up: bool) -> int:
    """A floor/ceiling at a voxel boundary splits over two layers: widen to the neighbour
    (above for a floor, below for a ceiling) when it is dense too."""
    step = 1 if up else -1
    neighbour = counts[values == k + step]
    if neighbour.size and neighbour[0] > 0.5 * counts[values == k][0]:
        return k + step
    return k


def ground_height(stats: VoxelStats) -> float | None:
    """Top of the floor: the lowest dense horizontal layer of occupied voxels."""
    floor, _ = floor_and_ceiling(stats)
    return floor


def floor_and_ceiling(stats: VoxelStats) -> tuple[float | None, float | None]:
    """Top of the floor and bottom of the ceiling (None when absent), from the histogram
    of occupied voxels per height layer: the lowest and highest dense layers, the ceiling
    at least 1.5 m above the floor."""
    values, counts = _occupied_layers(stats)
    if values.size == 0:
        return None, None
    r = stats.resolution
    dense = values[counts >= DENSE_LAYER * counts.max()]
    low = _dense_surface(values, counts, int(dense.min()), up=True)
    floor = (low + 1) * r
    high = _dense_surface(values, counts, int(dense.max()), up=False)
    ceiling = high * r
    return floor, (ceiling if ceiling >= floor + 1.5 else None)


def top_down_band(stats: VoxelStats) -> tuple[float, float]:
    """The default band: from 0.25 m above the floor, ``BAND_HEIGHT`` high, and ending
    0.25 m under the ceiling when there is one; all heights when no floor is found."""
    floor, ceiling = floor_and_ceiling(stats)
    if floor is None:
        return -math.inf, math.inf
    lo, hi = floor + 0.25, floor + 0.25 + BAND_HEIGHT
    if ceiling is not None:
        hi = min(hi, max(ceiling - 0.25, (floor + ceiling) / 2))
    return lo, hi


def crop_box(
    ijk2: NDArray[np.int64], margin: int = 2
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index bounds (lo, hi inclusive) of the ``CROP_PERCENTILES`` of these cells."""
    lo = np.floor(np.percentile(ijk2, CROP_PERCENTILES[0], axis=0)).astype(np.int64) - margin
    hi = np.ceil(np.percentile(ijk2, CROP_PERCENTILES[1], axis=0)).astype(np.int64) + margin
    return lo, hi


def _grid(
    ijk2: NDArray[np.int64], factor: int
) -> tuple[NDArray[np.int64], tuple[int, int], NDArray[np.int64]]:
    cells = np.floor_divide(ijk2, factor)
    lo = cells.min(axis=0)
    shape = tuple(int(v) for v in cells.max(axis=0) - lo + 1)
    return cells - lo, (shape[0], shape[1]), lo


def _coarsening(ijk2: NDArray[np.int64]) -> int:
    span = ijk2.max(axis=0) - ijk2.min(axis=0) + 1
    return max(1, int(math.ceil(float(span.max()) / MAX_IMAGE_CELLS)))


def _pick_per_cell(
    cells: NDArray[np.int64],
    shape: tuple[int, int],
    keys: tuple[NDArray[np.float64], ...],
) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """Per cell, the voxel with the largest ``keys`` (last key first, then the others in
    reverse order): (cells holding one, index of the voxel picked) — deterministic,
    whatever the storage order."""
    flat = cells[:, 0] * shape[1] + cells[:, 1]
    order = np.lexsort((*keys, flat))
    last = np.ones(order.size, dtype=bool)
    last[:-1] = flat[order][1:] != flat[order][:-1]
    pick = order[last]
    filled = np.zeros(shape[0] * shape[1], dtype=bool)
    filled[flat[pick]] = True
    index = np.zeros(shape[0] * shape[1], dtype=np.intp)
    index[flat[pick]] = pick
    return filled.reshape(shape), index.reshape(shape)


def _values(
    filled: NDArray[np.bool_], index: NDArray[np.intp], value: NDArray[np.float64]
) -> NDArray[np.float64]:
    return np.where(filled, value[index], np.nan)


def _max_per_cell(
    cells: NDArray[np.int64],
    shape: tuple[int, int],
    value: NDArray[np.float64],
    other: NDArray[np.float64],
    evidence: NDArray[np.float64],
    height: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per cell, the largest ``value`` and the ``other`` of the same voxel (NaN: empty);
    ties go to the voxel with most evidence, then the highest."""
    filled, index = _pick_per_cell(cells, shape, (height, evidence, value))
    return _values(filled, index, value), _values(filled, index, other)


def _draw_grid(ax: Any, grid: np.ndarray, extent: Any, vmax: float, cmap: str) -> Any:
    """Show a 2D grid (x along the first axis), NaN cells in grey; returns the image."""
    return ax.imshow(
        np.ma.masked_invalid(grid.T),
        origin="lower",
        extent=extent,
        cmap=_pyplot().get_cmap(cmap).with_extremes(bad="0.82"),
        vmin=0.0,
        vmax=vmax,
        interpolation="nearest",
        aspect="equal",
    )


def _image(
    plt: Any,
    grid: NDArray[np.float64],
    extent: list[float],
    title: str,
    label: str,
    path: Path,
    xlabel: str,
    ylabel: str,
    vmax: float = 1.0,
    cmap: str = "viridis",
) -> Path:
    fig, ax = plt.subplots(figsize=(7.5, 5.5), dpi=110)
    im = _draw_grid(ax, grid, extent, vmax, cmap)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    fig.colorbar(im, ax=ax, label=label, shrink=0.85)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def render_map(
    mapper: Mapper,
    out_dir: str | Path,
    z_min: float | None = None,
    z_max: float | None = None,
    slice_y: float | None = None,
    stamp: float | None = None,
    value: str = "most-likely",
    min_evidence: float = 0.0,
) -> RenderResult:
    """Write the pictures of ``mapper`` into ``out_dir``; return their paths.

    ``value``: per column, the largest ``"most-likely"`` DoO of the band (walls stand out;
    a voxel crossed once is 0, fully free) or the largest posterior ``"mean"`` DoO (it
    weighs the evidence against the map's prior; with the default prior a voxel seen
    briefly is near the prior's mean DoO, about 0.02 at 0.1 m). Never-observed cells are
    grey (unknown) in every picture, whatever the prior. The voxel
    drawn is the one with that largest value, ties to the most evidence (s), then the
    highest; the std picture shows its posterior std. ``min_evidence`` (metres of rays,
    s) leaves out voxels seen less than that: drawn as unobserved.
    """
    if value not in ("most-likely", "mean"):
        raise ValueError(f"value must be 'most-likely' or 'mean', got {value!r}")
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stats = mapper.voxels(stamp, min_evidence=min_evidence)
    result = RenderResult()
    if len(stats) == 0:
        raise ValueError("the map has no observed voxel (with that evidence): nothing to draw")
    r = mapper.resolution
    doo, std = stats.most_likely_doo, stats.std
    auto_lo, auto_hi = top_down_band(stats)
    lo_z = z_min if z_min is not None else auto_lo
    hi_z = z_max if z_max is not None else (auto_hi if z_min is None else lo_z + BAND_HEIGHT)
    result.band = (lo_z, hi_z)
    zc = stats.centers[:, 2]
    band = (zc >= lo_z) & (zc <= hi_z)
    if not np.any(band):
        band = np.ones(len(stats), dtype=bool)
        result.band = (-math.inf, math.inf)
    ijk2_all = stats.ijk[band][:, :2].astype(np.int64)
    box_lo, box_hi = crop_box(ijk2_all)
    inside = np.all((ijk2_all >= box_lo) & (ijk2_all <= box_hi), axis=1)
    band_index = np.flatnonzero(band)[inside]
    ijk2 = ijk2_all[inside]
    factor = _coarsening(ijk2)
    cells, shape, lo = _grid(ijk2, factor)
    shown = stats.mean_doo if value == "mean" else doo
    top, top_std = _max_per_cell(
        cells, shape, shown[band_index], std[band_index], stats.s[band_index], zc[band_index]
    )
    cell = r * factor
    extent = [lo[0] * cell, (lo[0] + shape[0]) * cell, lo[1] * cell, (lo[1] + shape[1]) * cell]
    result.extent = (extent[0], extent[1], extent[2], extent[3])
    result.top_down, result.top_down_std = top, top_std
    band_txt = _band_text(result.band)
    frame = mapper.frame_id or "map"
    result.files.append(
        _image(
            plt,
            top,
            extent,
            (
                f"Most likely degree of occupancy, highest in {band_txt}"
                if value == "most-likely"
                else f"Posterior mean degree of occupancy, highest in {band_txt}"
            ),
            "degree of occupancy 1 - exp(-n/s)",
            out / "doo_topdown.png",
            f"x [m] ({frame})",
            f"y [m] ({frame})",
        )
    )
    result.files.append(
        _image(
            plt,
            top_std,
            extent,
            f"Std of the degree of occupancy (same voxels, {band_txt})",
            "posterior std",
            out / "std_topdown.png",
            f"x [m] ({frame})",
            f"y [m] ({frame})",
            vmax=STD_MAX,
            cmap="magma",
        )
    )
    # vertical slice
    if slice_y is None:
        slice_y = float(np.median(stats.centers[:, 1]))
    result.slice_y = slice_y
    j = int(math.floor(slice_y / r))
    row = stats.ijk[:, 1] == j
    if np.any(row):
        xz = stats.ijk[row][:, [0, 2]].astype(np.int64)
        f2 = _coarsening(xz)
        cells2, shape2, lo2 = _grid(xz, f2)
        sdoo, sstd = _max_per_cell(
            cells2, shape2, doo[row], std[row], stats.s[row], stats.centers[row, 1]
        )
        c2 = r * f2
        ext2 = [lo2[0] * c2, (lo2[0] + shape2[0]) * c2, lo2[1] * c2, (lo2[1] + shape2[1]) * c2]
        aspect = (ext2[3] - ext2[2]) / max(ext2[1] - ext2[0], 1e-9)
        panel = min(max(7.0 * aspect, 1.2), 4.0)
        fig, axes = plt.subplots(2, 1, figsize=(9, 2 * panel + 1.6), dpi=110, sharex=True)
        for ax, grid, title, vmax, cmap in (
            (axes[0], sdoo, "most likely degree of occupancy", 1.0, "viridis"),
            (axes[1], sstd, "posterior std", STD_MAX, "magma"),
        ):
            im = _draw_grid(ax, grid, ext2, vmax, cmap)
            ax.set_title(f"Vertical slice y = {slice_y:.2f} m: {title}", fontsize=10)
            ax.set_ylabel("z [m]")
            fig.colorbar(im, ax=ax, fraction=0.03, pad=0.02)
        axes[1].set_xlabel(f"x [m] ({frame})")
        fig.tight_layout()
        path = out / "slice.png"
        fig.savefig(path)
        plt.close(fig)
        result.files.append(path)
    # histograms
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=110)
    bins = np.linspace(0, 1, 51)
    axes[0].hist(doo, bins=bins, color="tab:blue", label="observed voxels")
    axes[0].hist(
        doo[stats.n >= 1], bins=bins, color="tab:orange", alpha=0.7, label="with a return (n >= 1)"
    )
    axes[0].set_xlabel("most likely degree of occupancy")
    axes[1].hist(std, bins=np.linspace(0, STD_MAX, 51), color="tab:purple")
    axes[1].set_xlabel("posterior std of the degree of occupancy")
    for ax in axes:
        ax.set_yscale("log")
        ax.set_ylabel("voxels")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{len(stats):,} observed voxels of {r:g} m", fontsize=10)
    fig.tight_layout()
    path = out / "histogram.png"
    fig.savefig(path)
    plt.close(fig)
    result.files.append(path)
    histograms = mapper.reflectivity(stats.centers, stamp)
    if histograms is not None:
        drawn = _reflectivity_topdown(plt, stats, histograms, (box_lo, box_hi), out, frame)
        if drawn is not None:
            result.reflectivity = drawn[0]
            result.files.append(drawn[1])
    return result


def _reflectivity_topdown(
    plt: Any,
    stats: VoxelStats,
    histograms: tuple[ReflectivityBins, NDArray[np.float64]],
    box: tuple[NDArray[np.int64], NDArray[np.int64]],
    out: Path,
    frame: str,
) -> tuple[NDArray[np.float64], Path] | None:
    """``reflectivity_topdown.png``: per column (within ``box``, x-y voxel indices) the mean
    intensity of the lowest voxel holding returns; None when no voxel in the box holds any."""
    from matplotlib.colors import LogNorm

    bins, counts = histograms
    held = counts.sum(axis=1) > 0
    ijk2 = stats.ijk[:, :2].astype(np.int64)
    held &= np.all((ijk2 >= box[0]) & (ijk2 <= box[1]), axis=1)
    if not held.any():
        return None
    index = np.flatnonzero(held)
    factor = _coarsening(ijk2[index])
    cells, shape, lo = _grid(ijk2[index], factor)
    filled, pick = _pick_per_cell(
        cells, shape, (counts[index].sum(axis=1), -stats.centers[index, 2])
    )
    grid = _values(filled, pick, mean_value(counts[index], bins))
    edges = np.asarray(bins.edges, dtype=np.float64)
    vmin = float(edges[0] / 2) if edges.size and edges[0] > 0 else 1.0
    vmax = float(edges[-1] * 2) if edges.size and edges[-1] > 0 else 256.0
    cell = stats.resolution * factor
    extent = [lo[0] * cell, (lo[0] + shape[0]) * cell, lo[1] * cell, (lo[1] + shape[1]) * cell]
    fig, ax = plt.subplots(figsize=(7.5, 5.5), dpi=110)
    im = ax.imshow(
        np.ma.masked_invalid(grid.T), origin="lower", extent=extent,
        cmap=plt.get_cmap("inferno").with_extremes(bad="0.82"),
        norm=LogNorm(vmin=vmin, vmax=vmax), interpolation="nearest", aspect="equal",
    )  # fmt: skip
    ax.set_title(f"Mean {bins.field} of the lowest voxel with returns per column", fontsize=10)
    ax.set_xlabel(f"x [m] ({frame})")
    ax.set_ylabel(f"y [m] ({frame})")
    fig.colorbar(im, ax=ax, label=f"{bins.field} (mean of the voxel's histogram)", shrink=0.85)
    fig.tight_layout()
    path = out / "reflectivity_topdown.png"
    fig.savefig(path)
    plt.close(fig)
    return grid, path


def _band_text(band: tuple[float, float]) -> str:
    if not (math.isfinite(band[0]) or math.isfinite(band[1])):
        return "all heights"
    return f"z in [{band[0]:.2f}, {band[1]:.2f}] m"


def convergence_series(
    returns: int = 10,
    passes: int = 40,
    cell: float = 0.1,
    return_lengths: tuple[float, ...] = (0.01, 0.05, 0.1),
) -> dict[str, Any]:
    """One cell probed repeatedly: ``returns`` rays reflected in it, then ``passes`` rays
    crossing it (each adding ``cell`` metres). Per ray count: the classic occupancy
    probability, its std and hit probability; and for each length a reflected ray adds,
    the most likely DoO, its std and the hit probability of Eq. 34."""
    rays = np.arange(returns + passes + 1)
    hits = np.minimum(rays, returns)
    misses = rays - hits
    p = model.classic_occupancy(hits, misses)
    series: dict[str, Any] = {
        "rays": rays,
        "classic": {
            "value": p,
            "std": np.sqrt(p * (1 - p)),
            "p_hit": model.CLASSIC_P_HIT_OCCUPIED * p + model.CLASSIC_P_HIT_FREE * (1 - p),
        },
        "doo": {},
    }
    for ds in return_lengths:
        s = hits * ds + misses * cell
        n = hits.astype(np.float64)
        series["doo"][ds] = {
            "value": model.most_likely_doo(s, n),
            "std": model.std_doo(s, n),
            "p_hit": model.hit_probability(s, n, cell),
        }
    return series


def plot_convergence(out: str | Path, returns: int = 10, passes: int = 40) -> Path:
    """Write the Fig. 9-like picture to ``out`` (a .png path or a directory)."""
    plt = _pyplot()
    path = Path(out)
    if path.suffix.lower() != ".png":
        path.mkdir(parents=True, exist_ok=True)
        path = path / "convergence.png"
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
    data = convergence_series(returns, passes)
    rays = data["rays"]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8), dpi=110)
    keys = (
        ("value", "most likely value"),
        ("std", "standard deviation"),
        ("p_hit", "probability of a hit in the cell"),
    )
    for ax, (key, title) in zip(axes, keys, strict=True):
        ax.plot(rays, data["classic"][key], "k-", lw=2, label="occupancy grid p(o)")
        for ds, values in data["doo"].items():
            ax.plot(
                rays,
                values[key],
                ":",
                lw=2,
                marker=".",
                ms=3,
                label=f"degree of occupancy, Δs = {ds:g} m on a return",
            )
        ax.axvspan(0, returns, color="tab:red", alpha=0.08)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("rays assimilated")
        ax.set_ylim(-0.02, 1.02 if key != "std" else 0.55)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="center right")
    fig.suptitle(
        f"One 0.1 m cell: {returns} reflected rays (shaded), then {passes} passing through "
        "(Δs = 0.1 m). Classic model: p(d|o) = 0.47, p(d|free) = 0.2, prior 0.5",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
