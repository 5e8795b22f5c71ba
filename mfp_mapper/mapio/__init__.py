"""Map files: the single-file format, tiled maps, merging map files and atomic writes.
Imports the core; the core never imports it. ``load_map`` and ``save_map`` (from
``mapio.loading``) are imported lazily, so ``mapio.atomic`` stays light."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mfp_mapper.mapio.loading import load_map, save_map

__all__ = ["load_map", "save_map"]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module 'mfp_mapper.mapio' has no attribute {name!r}")
    value = getattr(importlib.import_module("mfp_mapper.mapio.loading"), name)
    globals()[name] = value
    return value
