"""Calibration files read strictly, in time linear in their length (microseconds a line): the YAML
and JSON that OpenCV's ``cv2.FileStorage`` writes, and ROS ``camera_info`` YAML as
``camera_calibration`` writes it. Nothing else is read: OpenCV's own parser can be held for seconds
by a few hundred bytes (a ``!!binary`` scalar), and a calibration comes from anyone who can post a
pair.

The YAML, line by line (blank lines and whole-line ``#`` comments anywhere)::

    %YAML:1.0 or %YAML 1.2, then ---         optional, as OpenCV writes them
    name: value                               a number, a string, or a flow list [1, 2, ...] of
                                              numbers (over several lines while its bracket is open)
    name: !!opencv-matrix                     then indented rows: n, cols: n, dt: d, data: [...]
    name: !!opencv-nd-matrix                  then indented sizes: [n] or [n, m], dt: d, data: [...]
    name:                                     then indented rows, cols, data (ROS), or `- number` lines
    name: {rows: n, cols: n, data: [...]}     ROS's flow form

The JSON (whole-line ``//`` comments allowed, as OpenCV writes them): one object whose values are
numbers, strings, lists of numbers and matrices ``{"type_id": "opencv-matrix", "rows", "cols",
"dt", "data"}`` (``opencv-nd-matrix``: ``sizes`` for rows and cols). Numbers are finite; a matrix
is one channel (``dt`` one of ``ucwsifdh``) of one or two dimensions, its data as many values as
its sizes say. Anything else (other tags, anchors, aliases, block scalars, nested maps, NaN) is a
RigError naming the entry.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np

__all__ = ["MAX_CALIBRATION_BYTES", "MAX_LINES", "RigError", "Value", "parse_entries"]

MAX_CALIBRATION_BYTES = 256 << 10
"""Largest calibration file (a calibration file is a few kilobytes)."""
MAX_LINES = 1000
"""Most lines of a calibration file (one has under a hundred): its cost stays a few milliseconds."""

Value = float | str | np.ndarray
"""An entry of a calibration file: a number, a string, or a float64 array (a list or a matrix)."""


class RigError(ValueError):
    """A calibration that cannot be used; ``field`` names what is wrong (e.g. ``"T"``)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field, self.reason = field, message


_HEADER = re.compile(r"%YAML[: ]1\.[0-2]")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_ENTRY = re.compile(r"([A-Za-z_][A-Za-z0-9_]*):(?: +(.*))?")
_NUMBER_TEXT = r"(?>[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)"  # atomic: never backtracks
_NUMBER = re.compile(_NUMBER_TEXT)
_NOT_FINITE = re.compile(r"[+-]?\.(?:inf|Inf|INF|nan|NaN|NAN)")
_LIST = re.compile(rf"\[ *(?:{_NUMBER_TEXT} *, *)*{_NUMBER_TEXT} *\]")
_LIST_HEAD = re.compile(rf"\[ *(?:{_NUMBER_TEXT} *, *)*")
_FLOW_MAP = re.compile(r"\{([^{}]*)\}")
_FLOW_ITEM = re.compile(r" *([A-Za-z_][A-Za-z0-9_]*): +(\[[^\[\]{}]*\]|[^ \[\]{},]+) *(?:,(?= *[A-Za-z_])|\Z)")
_QUOTED = re.compile(r"\"[^\"\\]*\"|'[^']*'")
_INDICATORS = "!&*|>%@`\"'#,?:-[]{}"
"""Where a plain YAML string may not start: tags, anchors, aliases, block scalars and the like."""
_MATRIX_TAGS = ("!!opencv-matrix", "!!opencv-nd-matrix")
_MATRIX_PARTS = {
    "opencv-matrix": ("rows", "cols", "dt", "data"),
    "opencv-nd-matrix": ("sizes", "dt", "data"),
    "ros": ("rows", "cols", "data"),
}
_NOT_FINITE_REASON = "holds a number that is not finite (NaN, infinite, or beyond 1.8e308)"
_DEPTHS = "ucwsifdh"
"""OpenCV's `dt` of one channel: (u)int8, (u)int16, int32, float32, float64, float16."""

Line = tuple[int, str]
"""A line's number (from 1) and its text, without trailing spaces."""


def parse_entries(text: str, source: str, prefix: str = "") -> dict[str, Value]:
    """The top-level entries of a calibration file, JSON where it starts with ``{``, else YAML.
    RigError naming ``prefix`` + the entry where one is not of the grammar above, or `source`
    where the file as a whole is not, or has no entry (an empty file)."""
    if len(text) > MAX_CALIBRATION_BYTES:
        raise RigError(source, f"larger than {MAX_CALIBRATION_BYTES >> 10} KiB (a calibration is a few kilobytes)")
    if text.count("\n") > MAX_LINES:
        raise RigError(source, f"more than {MAX_LINES} lines (a calibration has under a hundred)")
    read = _json_entries if text.lstrip().startswith("{") else _yaml_entries
    entries = read(text, source, prefix)
    if not entries:
        raise RigError(source, "the file is empty (no calibration entries)")
    return entries


def _not_read(source: str, problem: str) -> RigError:
    return RigError(source, f"not a YAML or JSON file as OpenCV or ROS write it: {problem}")


# --- YAML ------------------------------------------------------------------------------------------


def _yaml_entries(text: str, source: str, prefix: str) -> dict[str, Value]:
    numbered = ((number, line.rstrip()) for number, line in enumerate(text.split("\n"), 1))
    lines = [(number, line) for number, line in numbered if line and not line.lstrip().startswith("#")]
    position = 0
    if lines and _HEADER.fullmatch(lines[0][1]):
        if len(lines) < 2 or lines[1][1] != "---":
            raise _not_read(source, f"line {lines[0][0]}: a %YAML line is followed by ---")
        position = 2
    elif lines and lines[0][1] == "---":
        position = 1
    entries: dict[str, Value] = {}
    while position < len(lines):
        number, line = lines[position]
        entry = _ENTRY.fullmatch(line)
        if entry is None:
            raise _not_read(source, f"line {number}: expected `name: value` at the start of the line")
        name, rest = entry[1], entry[2] or ""
        field = prefix + name
        if rest in ("", *_MATRIX_TAGS):
            end = position + 1
            while end < len(lines) and lines[end][1].startswith(" "):
                end += 1
            value = _block(field, rest, lines[position + 1 : end])
        else:
            rest, end = _flow_text(rest, lines, position + 1)
            value = _value(field, rest)
        _add(entries, field, name, value)
        position = end
    return entries


def _flow_text(text: str, lines: list[Line], position: int) -> tuple[str, int]:
    """`text`, continued over the lines from `position` while a flow list or map it opens is open,
    and the position after them."""
    if not text.startswith(("[", "{")):
        return text, position
    parts, depth = [text], _depth(text)
    while depth > 0 and position < len(lines):
        line = lines[position][1].strip()
        parts.append(line)
        depth += _depth(line)
        position += 1
    return " ".join(parts), position


def _depth(text: str) -> int:
    return text.count("[") + text.count("{") - text.count("]") - text.count("}")


def _block(field: str, tag: str, lines: list[Line]) -> Value:
    """The indented lines under `name:` or `name: !!opencv-matrix`: a matrix's parts (`name: value`
    lines), or a list of numbers (`- number` lines, without a tag)."""
    if not lines:
        raise RigError(field, "has no value")
    indent = len(lines[0][1]) - len(lines[0][1].lstrip(" "))
    parts: dict[str, Value] = {}
    items: list[float] = []
    position = 0
    while position < len(lines):
        number, line = lines[position]
        body = line[indent:]
        if line[:indent].strip() or body.startswith(" "):
            raise RigError(field, f"line {number}: not at the indentation of the line above")
        if body.startswith("- "):
            items.append(_number(field, body[2:].strip()))
            position += 1
            continue
        part = _ENTRY.fullmatch(body)
        if part is None or part[2] is None:
            raise RigError(field, f"line {number}: expected `name: value` (a matrix's rows, cols, dt, data)")
        text, position = _flow_text(part[2], lines, position + 1)
        _add(parts, field, part[1], _value(field, text))
    if items and not parts and not tag:
        return np.array(items)
    if items:
        raise RigError(field, "neither a list of numbers nor a matrix")
    return _matrix(field, tag.removeprefix("!!") or "ros", parts)


def _value(field: str, text: str) -> Value:
    """One value on a line: a number, a flow list of numbers, a ROS flow map, or a string."""
    if text.startswith("["):
        return _list(field, text)
    if text.startswith("{"):
        return _flow_map(field, text)
    if _NUMBER.fullmatch(text) or _NOT_FINITE.fullmatch(text):
        return _number(field, text)
    if _QUOTED.fullmatch(text):
        return text[1:-1]
    if text[0] in _INDICATORS or ": " in text or " #" in text:
        raise RigError(
            field,
            f"{text[:32]!r} is not read: a value is a number, a string, a list of numbers or a matrix "
            "(no YAML tags but !!opencv-matrix, no anchors, aliases or block scalars)",
        )
    return text


def _list(field: str, text: str) -> np.ndarray:
    """A flow list of numbers, matched by one regular expression (a Python loop over 50,000 numbers
    would take 50 ms)."""
    if not _LIST.fullmatch(text):
        head = _LIST_HEAD.match(text)
        rest = text[head.end() :] if head is not None else text
        if _NOT_FINITE.match(rest):
            raise RigError(field, _NOT_FINITE_REASON)
        raise RigError(field, f"expected a list of numbers [1, 2, ...], got {rest[:32]!r} in it")
    values = np.array(text[1:-1].split(","), np.float64)
    if not np.isfinite(values).all():
        raise RigError(field, _NOT_FINITE_REASON)
    return values


def _flow_map(field: str, text: str) -> np.ndarray:
    """A ROS matrix written as a flow map: {rows: n, cols: n, data: [...]}."""
    inner = _FLOW_MAP.fullmatch(text)
    if inner is None:
        raise RigError(field, f"expected a matrix {{rows: n, cols: n, data: [...]}}, got {text[:32]!r}")
    parts: dict[str, Value] = {}
    position = 0
    while position < len(inner[1]):
        item = _FLOW_ITEM.match(inner[1], position)
        if item is None:
            raise RigError(field, f"expected a matrix {{rows: n, cols: n, data: [...]}}, got {text[:32]!r}")
        _add(parts, field, item[1], _value(field, item[2]))
        position = item.end()
    return _matrix(field, "ros", parts)


def _number(field: str, token: str) -> float:
    if _NUMBER.fullmatch(token):
        return _finite(field, float(token))
    if _NOT_FINITE.fullmatch(token):
        raise RigError(field, _NOT_FINITE_REASON)
    raise RigError(field, f"expected a number, got {token[:32]!r}")


def _finite(field: str, value: float) -> float:
    if not math.isfinite(value):
        raise RigError(field, _NOT_FINITE_REASON)
    return value


def _add(values: dict[str, Value], field: str, name: str, value: Value) -> None:
    if name in values:
        raise RigError(field, f"`{name}` is given twice")
    values[name] = value


# --- matrices --------------------------------------------------------------------------------------


def _matrix(field: str, kind: str, parts: dict[str, Value]) -> np.ndarray:
    """The float64 array of a matrix of `kind` (a key of _MATRIX_PARTS) from its parts, checked."""
    names = _MATRIX_PARTS[kind]
    if set(parts) != set(names):
        given = ", ".join(parts) or "nothing"
        raise RigError(field, f"a matrix ({kind}) has exactly {', '.join(names)}; got {given}")
    dt = parts.get("dt", "d")
    if not (isinstance(dt, str) and len(dt) == 1 and dt in _DEPTHS):
        raise RigError(field, f"dt {str(dt)[:16]!r} is not a type of one channel (one of {', '.join(_DEPTHS)})")
    if kind == "opencv-nd-matrix":
        sizes = parts["sizes"]
        if not (isinstance(sizes, np.ndarray) and sizes.ndim == 1 and sizes.size <= 2):
            raise RigError(field, "sizes: a matrix here has one or two dimensions, [n] or [rows, cols]")
        shape = [_size(field, "sizes", size) for size in sizes.tolist()]
    else:
        shape = [_size(field, name, parts[name]) for name in ("rows", "cols")]
    data = parts["data"]
    if not (isinstance(data, np.ndarray) and data.ndim == 1):
        raise RigError(field, "data: expected a list of numbers")
    if math.prod(shape) != data.size:
        sizes_text = "x".join(f"{size:g}" for size in shape)
        raise RigError(field, f"a {sizes_text} matrix has {math.prod(shape):g} values, its data {data.size}")
    return data.reshape([int(size) for size in shape])


def _size(field: str, name: str, value: Value) -> float:
    if not (isinstance(value, float) and value >= 1 and value.is_integer()):
        raise RigError(field, f"{name}: expected a positive whole number, got {str(value)[:32]}")
    return value


# --- JSON ------------------------------------------------------------------------------------------


def _json_entries(text: str, source: str, prefix: str) -> dict[str, Value]:
    lines = ("" if line.lstrip().startswith("//") else line for line in text.split("\n"))  # OpenCV's comments
    try:
        document = json.loads("\n".join(lines), parse_int=float, parse_constant=_no_constant, object_pairs_hook=_unique)
    except (ValueError, RecursionError) as error:
        raise _not_read(source, str(error)) from None
    if not isinstance(document, dict):
        raise _not_read(source, "a JSON calibration is one object")
    entries: dict[str, Value] = {}
    for name, value in document.items():
        if not _NAME.fullmatch(name):
            raise _not_read(source, f"{name[:32]!r} is not a name of letters, digits and _")
        entries[name] = _json_value(prefix + name, value)
    return entries


def _json_value(field: str, value: object, in_matrix: bool = False) -> Value:
    """A JSON value as an entry: a number, a string, a list of numbers or (not within a matrix) a matrix."""
    if isinstance(value, float):
        return _finite(field, value)
    if isinstance(value, str):
        return value
    if isinstance(value, list) and value and all(isinstance(item, float) for item in value):
        return np.array([_finite(field, item) for item in value])
    if isinstance(value, dict) and not in_matrix:
        kind = value.get("type_id")
        if kind not in ("opencv-matrix", "opencv-nd-matrix"):
            raise RigError(field, f"an object is a matrix with type_id opencv-matrix, got type_id {str(kind)[:32]!r}")
        parts = {name: _json_value(field, part, True) for name, part in value.items() if name != "type_id"}
        return _matrix(field, kind, parts)
    raise RigError(field, f"expected a number, a string, a list of numbers or a matrix, got {str(value)[:32]}")


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a finite number")


def _unique(pairs: list[tuple[str, object]]) -> dict[str, object]:
    values = dict(pairs)
    if len(values) != len(pairs):
        raise ValueError("an object gives a name twice")
    return values
