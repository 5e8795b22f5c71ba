"""mfp_mapper: lidar mapping with the mean-free-path (degree of occupancy) model.

The public API (``Mapper``, ``VoxelStats``, ``IntegrationSummary``, ``MapFileError``,
``CoreError``, ``ScanTooLargeError``) is
imported lazily, so ``import mfp_mapper`` and ``mfp-mapper --help`` do not load numba.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from mfp_mapper.config.names import VERSION

if TYPE_CHECKING:
    from mfp_mapper.core.errors import CoreError, ScanTooLargeError
    from mfp_mapper.core.mapper import IntegrationSummary, Mapper, VoxelStats
    from mfp_mapper.mapio.mapfile import MapFileError

__all__ = [
    "CoreError",
    "IntegrationSummary",
    "MapFileError",
    "Mapper",
    "ScanTooLargeError",
    "VoxelStats",
]
__version__ = VERSION

_LAZY = {
    "IntegrationSummary": "mfp_mapper.core.mapper",
    "Mapper": "mfp_mapper.core.mapper",
    "VoxelStats": "mfp_mapper.core.mapper",
    "MapFileError": "mfp_mapper.mapio.mapfile",
    "CoreError": "mfp_mapper.core.errors",
    "ScanTooLargeError": "mfp_mapper.core.errors",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mfp_mapper' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
