"""Pictures of a map (``mfp-mapper render``) and of the model (``plot-convergence``).

matplotlib with the Agg backend (no display needed). ``render_map`` writes

- ``doo_topdown.png``: per column the highest most likely degree of occupancy (DoO) in a
  height band (default: from just above the ground to 2.5 m above it);
- ``std_topdown.png``: the posterior std of that same voxel;
- ``slice.png``: a vertical x-z slice at one y: most likely DoO and std;
- ``histogram.png``: histograms of the most likely DoO and of the std.

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

MAX_IMAGE_CELLS = 1600
"""Top-down and slice images are coarsened so that no side exceeds this many cells."""


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


def ground_height(stats: VoxelStats) -> float | None:
    """Top of the horizontal voxel layer holding the most confidently occupied voxels."""
    occ = stats.observed & (stats.most_likely_doo > 0.5) & (stats.n >= 1)
    if not np.any(occ):
        return None
    k = stats.ijk[occ, 2]
    values, counts = np.unique(k, return_counts=True)
    best = int(values[np.argmax(counts)])
    # a floor at a voxel boundary splits over two layers: take the upper if it is dense too
    upper = counts[values == best + 1]
    if upper.size and upper[0] > 0.5 * counts.max():
        best += 1
    return (best + 1) * stats.resolution


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


def _max_per_cell(
    cells: NDArray[np.int64],
    shape: tuple[int, int],
    value: NDArray[np.float64],
    other: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per cell, the largest ``value`` and the ``other`` of the same voxel (NaN: empty)."""
    flat = cells[:, 0] * shape[1] + cells[:, 1]
    order = np.lexsort((value, flat))
    last = np.ones(order.size, dtype=bool)
    last[:-1] = flat[order][1:] != flat[order][:-1]
    pick = order[last]
    top = np.full(shape[0] * shape[1], np.nan)
    oth = np.full(shape[0] * shape[1], np.nan)
    top[flat[pick]] = value[pick]
    oth[flat[pick]] = other[pick]
    return top.reshape(shape), oth.reshape(shape)


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
) -> RenderResult:
    """Write the pictures of ``mapper`` into ``out_dir``; return their paths."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stats = mapper.voxels(stamp)
    result = RenderResult()
    if len(stats) == 0:
        raise ValueError("the map has no observed voxel: nothing to draw")
    r = mapper.resolution
    doo, std = stats.most_likely_doo, stats.std
    ground = ground_height(stats)
    lo_z = z_min if z_min is not None else (ground + 0.25 if ground is not None else -math.inf)
    hi_z = z_max if z_max is not None else (lo_z + 2.25 if math.isfinite(lo_z) else math.inf)
    result.band = (lo_z, hi_z)
    zc = stats.centers[:, 2]
    band = (zc >= lo_z) & (zc <= hi_z)
    if not np.any(band):
        band = np.ones(len(stats), dtype=bool)
        result.band = (-math.inf, math.inf)
    ijk2 = stats.ijk[band][:, :2].astype(np.int64)
    factor = _coarsening(ijk2)
    cells, shape, lo = _grid(ijk2, factor)
    top, top_std = _max_per_cell(cells, shape, doo[band], std[band])
    cell = r * factor
    extent = [lo[0] * cell, (lo[0] + shape[0]) * cell, lo[1] * cell, (lo[1] + shape[1]) * cell]
    band_txt = _band_text(result.band)
    frame = mapper.frame_id or "map"
    result.files.append(
        _image(
            plt,
            top,
            extent,
            f"Most likely degree of occupancy, highest in {band_txt}",
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
            vmax=float(model.UNKNOWN_STD),
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
        sdoo, sstd = _max_per_cell(cells2, shape2, doo[row], std[row])
        c2 = r * f2
        ext2 = [lo2[0] * c2, (lo2[0] + shape2[0]) * c2, lo2[1] * c2, (lo2[1] + shape2[1]) * c2]
        aspect = (ext2[3] - ext2[2]) / max(ext2[1] - ext2[0], 1e-9)
        panel = min(max(7.0 * aspect, 1.2), 4.0)
        fig, axes = plt.subplots(2, 1, figsize=(9, 2 * panel + 1.6), dpi=110, sharex=True)
        for ax, grid, title, vmax, cmap in (
            (axes[0], sdoo, "most likely degree of occupancy", 1.0, "viridis"),
            (axes[1], sstd, "posterior std", float(model.UNKNOWN_STD), "magma"),
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
    axes[1].hist(std, bins=np.linspace(0, float(model.UNKNOWN_STD), 51), color="tab:purple")
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
    return result


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
