"""mfp_mapper: lidar mapping with the mean-free-path (degree of occupancy) model."""

from mfp_mapper.mapfile import MapFileError
from mfp_mapper.mapper import IntegrationSummary, Mapper, VoxelStats

__all__ = ["IntegrationSummary", "MapFileError", "Mapper", "VoxelStats"]
__version__ = "0.1.0"
