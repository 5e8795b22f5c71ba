"""Frame ids as parameters, messages and recordings give them: tf1 wrote them with a leading
slash, which tf2 and RViz reject; every frame id the package reads goes through
``frame_name`` once."""

from __future__ import annotations


def frame_name(frame: str) -> str:
    """A frame id without tf1's leading slash ("/base_link" -> "base_link")."""
    return str(frame).lstrip("/")
