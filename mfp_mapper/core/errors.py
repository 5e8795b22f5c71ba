"""Errors the core raises for inputs it refuses; the map is unchanged when they are raised."""

from __future__ import annotations


class CoreError(Exception):
    """Base of the core's refusals: catch this to log and go on."""


class ScanTooLargeError(CoreError):
    """A scan that could need more map memory than ``max_voxels`` allows: refused whole,
    before any of its rays is added."""
