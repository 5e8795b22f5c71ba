"""Poses to files: a TUM trajectory (``t x y z qx qy qz qw``) and a per-scan confidence
file (JSON lines) beside it."""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from mfp_mapper.mapio.atomic import write_text_atomic

__all__ = ["confidence_path_for", "write_confidence", "write_tum_poses"]


def write_tum_poses(
    path: str | Path, stamps: ArrayLike, positions: ArrayLike, quaternions: ArrayLike
) -> None:
    """Write poses as TUM lines ``t x y z qx qy qz qw`` (stamps in seconds), atomically."""
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quaternions, dtype=np.float64).reshape(-1, 4)
    if not (len(t) == len(p) == len(q)):
        raise ValueError(f"{len(t)} stamps, {len(p)} positions, {len(q)} quaternions")
    lines = [
        f"{ti:.9f} {pi[0]:.6f} {pi[1]:.6f} {pi[2]:.6f} {qi[0]:.9f} {qi[1]:.9f} {qi[2]:.9f} "
        f"{qi[3]:.9f}"
        for ti, pi, qi in zip(t, p, q, strict=True)
    ]
    write_text_atomic(path, "# t x y z qx qy qz qw\n" + "".join(line + "\n" for line in lines))


def confidence_path_for(poses_path: str | Path) -> Path:
    """Where the per-scan confidence of a pose file goes: ``<file>.confidence.jsonl``."""
    p = Path(poses_path)
    return p.with_name(p.name + ".confidence.jsonl")


def _clean(value: object) -> object:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Sequence) and not isinstance(value, str):
        return [_clean(v) for v in value]
    return value


def write_confidence(path: str | Path, rows: Iterable[dict[str, object]]) -> None:
    """One JSON object per scan (non-finite numbers as null), atomically."""
    text = "".join(json.dumps({k: _clean(v) for k, v in row.items()}) + "\n" for row in rows)
    write_text_atomic(path, text)
