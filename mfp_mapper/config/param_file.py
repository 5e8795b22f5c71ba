"""Read a ROS 2 parameter file as rcl reads it for one node, without ROS.

rcl (``rcl_yaml_param_parser``) and PyYAML disagree on what a value is (``1e3`` is a double
to rcl and a string to PyYAML; ``010`` is the integer 8 to rcl), and rclpy then rejects a value
of the wrong type (``resolution: 1`` is an INTEGER, the node wants a DOUBLE). So the file is
parsed with PyYAML's composer only, and every scalar is typed here with rcl's rules:

- quoted, or tagged ``!!str``: a string;
- ``y Y yes Yes YES true True TRUE on On ON`` (and the ``n``/``no``/``false``/``off`` set):
  a bool;
- what C ``strtol(text, 0)`` reads whole (``12``, ``+5``, ``0x10``, ``010`` octal): an integer;
- ``.inf``/``.nan`` spellings and what C ``strtod`` reads whole (``1.``, ``1e3``, ``inf``): a
  double;
- anything else: a string. A sequence holds one type (else an error); ``[]`` is "not set".

Sections: a node's parameters are those of every top-level entry (``/**``, ``mfp_mapper``,
``/*``, ``/**/mfp_mapper``... with ``ns/`` nesting) whose name matches the node's fully
qualified name, entries taken in the order they first appear, a later one overriding an
earlier one; an entry repeated later in the file is merged into its first appearance. The
``ros__parameters`` key is required and nested keys are joined with ``.``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

NODE_NAME = "mfp_mapper"
PARAMS_KEY = "ros__parameters"

_TRUE = {"y", "Y", "yes", "Yes", "YES", "true", "True", "TRUE", "on", "On", "ON"}
_FALSE = {"n", "N", "no", "No", "NO", "false", "False", "FALSE", "off", "Off", "OFF"}
_INF = {".inf", ".Inf", ".INF", "+.inf", "+.Inf", "+.INF"}
_NEG_INF = {"-.inf", "-.Inf", "-.INF"}
_NAN = {".nan", ".NaN", ".NAN"}
_STRTOL = re.compile(r"\s*[+-]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)")
_STRTOD = re.compile(
    r"\s*[+-]?("
    r"(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?"
    r"|0[xX]([0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)([pP][+-]?\d+)?"
    r"|inf(inity)?|nan(\([0-9A-Za-z_]*\))?"
    r")",
    re.IGNORECASE,
)
_STR_TAG = "tag:yaml.org,2002:str"
_UNTAGGED = "!untagged"
_INT64 = 2**63


class ParamFileError(ValueError):
    """The file is not a parameter file rcl can read: says where and why."""


def scalar_value(text: str, quoted: bool = False, str_tag: bool = False) -> Any:
    """One scalar typed as rcl types it: bool, int, float or str."""
    if quoted or str_tag:
        return text
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    if _STRTOL.fullmatch(text):
        value = _strtol(text.strip())
        if -_INT64 <= value < _INT64:
            return value  # strtol overflows to ERANGE: then it is read as a double
    if text in _INF:
        return math.inf
    if text in _NEG_INF:
        return -math.inf
    if text in _NAN:
        return math.nan
    if _STRTOD.fullmatch(text):
        return _strtod(text.strip())
    return text


def _strtol(body: str) -> int:
    sign = -1 if body.startswith("-") else 1
    digits = body.lstrip("+-")
    if digits[:2] in ("0x", "0X"):
        return sign * int(digits, 16)
    return sign * int(digits, 8 if digits.startswith("0") else 10)


def _strtod(body: str) -> float:
    sign = -1.0 if body.startswith("-") else 1.0
    digits = body.lstrip("+-")
    if digits[:2] in ("0x", "0X"):
        return sign * float.fromhex(digits)
    if digits.lower().startswith("nan"):
        return math.nan
    return sign * float(digits)


def _loader() -> Any:
    """A PyYAML loader that leaves untagged scalars untyped (rcl types them, not PyYAML)."""
    import yaml

    class Loader(yaml.SafeLoader):
        def resolve(self, kind: Any, value: Any, implicit: Any) -> Any:
            if kind is yaml.ScalarNode:
                return _UNTAGGED
            return super().resolve(kind, value, implicit)

    return Loader


def _line(node: Any) -> int:
    return int(node.start_mark.line) + 1


def _value(node: Any) -> Any:
    import yaml

    if isinstance(node, yaml.ScalarNode):
        if node.value == "" and node.style is None:
            raise ParamFileError(f"No value at line {_line(node)}")
        return scalar_value(node.value, node.style in ("'", '"'), node.tag == _STR_TAG)
    if isinstance(node, yaml.SequenceNode):
        items = []
        for item in node.value:
            if not isinstance(item, yaml.ScalarNode):
                raise ParamFileError(f"Sequences can only hold scalars, at line {_line(item)}")
            items.append(_value(item))
        if not items:
            return None  # rcl: an empty sequence leaves the parameter not set
        first = _kind(items[0])
        for item, child in zip(items, node.value, strict=True):
            if _kind(item) != first:
                raise ParamFileError(
                    f"Sequence should be of same type. Value type '{_kind(item)}' do not "
                    f"belong at line_num {_line(child)}"
                )
        return items
    raise ParamFileError(f"Unexpected mapping at line {_line(node)}")


def _kind(value: Any) -> str:
    return {bool: "bool", int: "integer", float: "double", str: "string"}[type(value)]


def _key(node: Any) -> str:
    import yaml

    if not isinstance(node, yaml.ScalarNode):
        raise ParamFileError(f"A key must be a scalar, at line {_line(node)}")
    return str(node.value)


def _parameters(node: Any, prefix: str, out: dict[str, Any]) -> None:
    import yaml

    if not isinstance(node, yaml.MappingNode):
        raise ParamFileError(f"{PARAMS_KEY} must hold a mapping, at line {_line(node)}")
    for key_node, value_node in node.value:
        name = prefix + _key(key_node)
        if isinstance(value_node, yaml.MappingNode):
            _parameters(value_node, name + ".", out)
        else:
            out[name] = _value(value_node)


def _sections(node: Any, path: str, out: dict[str, dict[str, Any]]) -> None:
    import yaml

    if not isinstance(node, yaml.MappingNode):
        raise ParamFileError(f"Cannot have a value before {PARAMS_KEY} at line {_line(node)}")
    for key_node, value_node in node.value:
        key = _key(key_node)
        if key == PARAMS_KEY:
            if not path:
                raise ParamFileError(f"{PARAMS_KEY} needs a node name above it")
            _parameters(value_node, "", out.setdefault(path, {}))
        else:
            _sections(value_node, f"{path}/{key}" if path else key, out)


def node_name_matches(pattern: str, fqn: str) -> bool:
    """rcl's match of a section name: ``/**`` any number of tokens, ``*`` one token."""
    pattern = pattern if pattern.startswith("/") else "/" + pattern
    regex = "".join(
        "(/[^/]+)*" if token == "**" else "/[^/]+" if token == "*" else "/" + re.escape(token)
        for token in pattern.split("/")[1:]
    )
    return re.fullmatch(regex, fqn) is not None


def yaml_error_line(err: Exception) -> str:
    """A YAML error on one line: ``line L, column C: what`` (1-based, as editors count)."""
    mark = getattr(err, "problem_mark", None) or getattr(err, "context_mark", None)
    what = " ".join(
        str(part) for part in (getattr(err, "context", None), getattr(err, "problem", None)) if part
    ) or " ".join(str(err).split())
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return f"not YAML: {where}{what}"


def read_sections(path: str | Path) -> dict[str, dict[str, Any]]:
    """Section name -> parameters, in the order the sections first appear (ParamFileError)."""
    import yaml

    p = Path(path)
    try:
        root = yaml.compose(p.read_text(), Loader=_loader())
    except OSError as err:
        raise ParamFileError(f"cannot read the parameter file: {err}") from None
    except yaml.YAMLError as err:
        raise ParamFileError(yaml_error_line(err)) from None
    sections: dict[str, dict[str, Any]] = {}
    if root is None:
        return sections
    try:
        _sections(root, "", sections)
    except ParamFileError as err:
        raise ParamFileError(f"not a ROS 2 parameter file: {err}") from None
    return sections


def load_node_parameters(
    path: str | Path, node_name: str = NODE_NAME, namespace: str = "/"
) -> dict[str, Any]:
    """The parameter overrides node ``namespace/node_name`` gets from this file."""
    fqn = namespace.rstrip("/") + "/" + node_name
    values: dict[str, Any] = {}
    for section, params in read_sections(path).items():
        if node_name_matches(section, fqn):
            values.update(params)
    return values
