"""One setting as a field of a settings section: ``setting(...)``, ``Setting`` and ``Section``.

A section (``mfp_mapper.config.sections``) is a frozen dataclass whose fields are made by
``setting``: each field carries its ``Setting`` (ROS name, description, range, CLI flag, run-time
change, where it applies, "<= 0 means no limit") in its dataclass metadata. This module is
plain data and imports neither ROS nor numpy.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

XyzRpy = tuple[tuple[float, float, float], tuple[float, float, float]]
"""A rigid mounting as configured: ([x, y, z] metres, fixed-axis [roll, pitch, yaw] radians)."""


def xyz_rpy(translation: Any, rpy: Any) -> XyzRpy:
    """An ``XyzRpy`` from two triples of finite numbers; ValueError otherwise."""
    t = tuple(float(v) for v in translation)
    r = tuple(float(v) for v in rpy)
    if len(t) != 3 or len(r) != 3 or not all(math.isfinite(v) for v in t + r):
        raise ValueError(f"an extrinsic needs 3 + 3 finite numbers, got {t} and {r}")
    return (t[0], t[1], t[2]), (r[0], r[1], r[2])


NO_LIMIT_Z = 1.0e6
"""The "no limit" value of the occupancy grid's height band (metres)."""

NO_LIMIT_BAND = 1.0e12
"""The "no limit" value of the point-cloud band ``point_cloud_min/max_x/y/z`` (metres), its
default and the bound of its range: beyond every Earth-fixed coordinate (UTM northings reach
1e7 m, ECEF 6.4e6 m), so a geo-referenced map frame needs no setting."""

Applies = Literal["node", "replay", "both"]
Unlimited = Literal["inf", "none", "cores"]

AUTOMATIC_THREADS_MAX = 4
"""The most threads "0: automatic" gives (``automatic_threads``): four threads walked a scan
1.6-2.7x as fast as one on idle cores, two 1.2-1.6x (docs/performance.md "Two threads")."""

METADATA_KEY = "setting"
"""The key of a section field's ``Setting`` in its dataclass metadata."""


@dataclass(frozen=True)
class Setting:
    """One setting. ``type`` is bool, int, float, str or list (of floats, ``length`` long).

    ``unlimited``: a value <= 0 means "no limit" to the core: ``inf`` or ``None`` (``cores``:
    as many threads as ``automatic_threads`` gives)
    (``core_value`` applies it). ``flag``: the ``replay`` CLI flag; for a bool it switches the
    default off (``--no-deskew``) or on (``--tf``). ``section``/``field``: where it is held
    (``NodeConfig``/``ReplayOptions`` attribute ``section``, its field ``field``).
    """

    name: str
    type: type
    default: Any
    description: str
    lo: float | None = None
    hi: float | None = None
    dynamic: bool = False
    """Can be changed at run time with ``ros2 param set``; all others are read-only."""
    applies: Applies = "node"
    flag: str | None = None
    unlimited: Unlimited | None = None
    length: int | None = None
    metavar: tuple[str, ...] | None = None
    section: str = ""
    field: str = ""

    @property
    def is_parameter(self) -> bool:
        """A ROS parameter of the node (declared, in the YAML, accepted by --config)."""
        return self.applies in ("node", "both")

    @property
    def in_replay(self) -> bool:
        """Read by the replay (``ReplayOptions``) and, with a flag, the ``replay`` CLI."""
        return self.applies in ("replay", "both")

    @property
    def ros_type(self) -> str:
        """The rclpy ``Parameter.Type`` name this setting is declared with."""
        return {bool: "BOOL", int: "INTEGER", float: "DOUBLE", str: "STRING"}.get(
            self.type, "DOUBLE_ARRAY"
        )

    def core_value(self, value: Any) -> Any:
        """The value the core (Mapper, replay) takes: "<= 0 means no limit" applied."""
        if self.unlimited is not None and value is not None and value <= 0:
            if self.unlimited == "cores":
                return automatic_threads()
            return math.inf if self.unlimited == "inf" else None
        return value

    @property
    def core_default(self) -> Any:
        return self.core_value(self.default)

    def held(self, value: Any) -> Any:
        """A value as a section holds it: a list setting as a tuple (sections are frozen)."""
        return tuple(float(v) for v in value) if self.type is list and value is not None else value

    def check_range(self, value: Any) -> str | None:
        """Why ``value`` is outside the range, in rclpy's words; None when inside."""
        if self.lo is None or self.hi is None or self.type not in (int, float):
            return None
        if self.type is float:
            rel = 1e-6  # rclpy Node.PARAM_REL_TOL: values at the edges are accepted
            if math.isclose(value, self.lo, rel_tol=rel) or math.isclose(
                value, self.hi, rel_tol=rel
            ):
                return None
            sep = " "
        else:
            if value in (self.lo, self.hi):
                return None
            sep = ". "
        if self.lo < value < self.hi:
            return None
        lo, hi = (float(self.lo), float(self.hi)) if self.type is float else (self.lo, self.hi)
        return f"Parameter {self.name} out of range{sep}Min: {lo}, Max: {hi}, value: {value}"


def setting(
    default: Any,
    description: str,
    lo: float | None = None,
    hi: float | None = None,
    *,
    type: type | None = None,  # noqa: A002 - the Setting's attribute of that name
    name: str | None = None,
    dynamic: bool = False,
    applies: Applies = "node",
    flag: str | None = None,
    unlimited: Unlimited | None = None,
    length: int | None = None,
    metavar: tuple[str, ...] | None = None,
) -> Any:
    """A section field that is a setting (``dataclasses.field`` with its ``Setting``).

    ``type``: needed only when ``default`` is None (a replay setting with no default); a list
    setting takes a tuple default (the section holds a tuple, ROS and the YAML a list).
    ``name``: the ROS/YAML name when it is not the section's ``PREFIX`` + the field name (a
    dotted name such as ``prior.shape`` held as ``prior_shape``).
    """
    kind = type or (list if isinstance(default, tuple) else default.__class__)
    spec = Setting(
        name or "",
        kind,
        list(default) if isinstance(default, tuple) else default,
        description,
        lo,
        hi,
        dynamic,
        applies,
        flag,
        unlimited,
        length,
        metavar,
    )
    return dataclasses.field(default=default, metadata={METADATA_KEY: spec})


class Section:
    """The base of a settings section: a frozen dataclass whose fields are ``setting``s.

    ``PREFIX`` starts the ROS name of each field (``localization.``); a field's name is its
    setting's name without the prefix, '.' -> '_'.
    """

    PREFIX: ClassVar[str] = ""
    KEY: ClassVar[str] = ""
    """The attribute holding this section in ``NodeConfig`` and ``ReplayOptions``."""
    TITLE: ClassVar[str] = ""
    """The section's heading in the documentation's parameter table."""

    @classmethod
    def settings(cls) -> tuple[Setting, ...]:
        """The section's settings, complete (name, type, section, field), in field order."""
        return _section_settings(cls)

    def core(self, field: str) -> Any:
        """A field's value as the core takes it ("<= 0 means no limit" applied)."""
        return _section_fields(type(self))[field].core_value(getattr(self, field))


_SETTINGS_OF: dict[type, tuple[Setting, ...]] = {}
_FIELDS_OF: dict[type, dict[str, Setting]] = {}


def _section_settings(cls: type[Section]) -> tuple[Setting, ...]:
    """A section's settings, made once per class from its fields' metadata."""
    found = _SETTINGS_OF.get(cls)
    if found is not None:
        return found
    out = []
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        spec = f.metadata.get(METADATA_KEY)
        if spec is None:
            raise TypeError(f"{cls.__name__}.{f.name} is not a setting (use setting())")
        name = spec.name or cls.PREFIX + f.name
        if name.removeprefix(cls.PREFIX).replace(".", "_") != f.name:
            raise TypeError(f"{cls.__name__}.{f.name}: the field must be named after {name}")
        out.append(dataclasses.replace(spec, name=name, section=cls.KEY, field=f.name))
    _SETTINGS_OF[cls] = tuple(out)
    return _SETTINGS_OF[cls]


def _section_fields(cls: type[Section]) -> dict[str, Setting]:
    if cls not in _FIELDS_OF:
        _FIELDS_OF[cls] = {s.field: s for s in _section_settings(cls)}
    return _FIELDS_OF[cls]


def automatic_threads() -> int:
    """The threads of "0: automatic": the cores this process may run on (its CPU affinity, as
    a container or ``taskset`` limits it; else the machine's), at most
    ``AUTOMATIC_THREADS_MAX``."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, AUTOMATIC_THREADS_MAX))
