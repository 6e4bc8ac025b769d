"""Calibration files: the YAML and JSON that OpenCV's ``cv2.FileStorage`` writes, read strictly by a
parser of that dialect alone, in time linear in their length (microseconds a line); and ROS
``camera_info`` files, read by PyYAML's safe loader in any YAML style. Nothing else is read:
OpenCV's own parser can be held for seconds by a few hundred bytes (a ``!!binary`` scalar), and a
calibration comes from anyone who can post a pair.

Which reader a file gets is told by its top-level names. A line that starts with a name only an
OpenCV calibration has (K1, D1, K2, D2, T, image_size) makes it OpenCV's at once; else PyYAML
composes the file (nodes only, nothing constructed) and its names tell: ROS's make it a
camera_info, R, image_width or image_height alone an OpenCV calibration (where PyYAML cannot
compose it, the names its lines start with tell). A file of neither is refused naming both forms;
an OpenCV file given as one of a pair of ROS camera_info files is refused saying to send one OpenCV
file or two camera_info files.

**ROS camera_info** (one camera; a stereo camera is two files), through ``yaml`` with its safe
loader (plain data, never Python objects), flow or block style, JSON too:

- as ``camera_calibration`` and ``camera_info_manager`` write it: image_width, image_height,
  camera_name, camera_matrix, distortion_model, distortion_coefficients, rectification_matrix,
  projection_matrix, each matrix ``{rows: n, cols: n, data: [...]}``;
- a ``sensor_msgs/CameraInfo`` message as ``ros2 topic echo`` (d, k, r, p) or ROS 1's
  ``rostopic echo`` (D, K, R, P) print it: height, width, distortion_model and the flat lists,
  beside the header, binning and roi, which are left unread (one message: a trailing ``---`` is
  fine).

Their entries come back under the first form's names (k is ``camera_matrix``). The
distortion_model is plumb_bob or rational_polynomial (OpenCV's lens model; ROS's equidistant is
another). Numbers are finite (1e-05 without a dot is a number, as in YAML 1.2). YAML aliases are
refused: PyYAML shares an aliased value rather than copying it, but a few hundred bytes of nested
aliases then read as a list of 9^9 numbers, gigabytes to convert. Names given twice are refused
(PyYAML would keep the last).

**OpenCV's YAML**, line by line (blank lines and whole-line ``#`` comments anywhere)::

    %YAML:1.0 or %YAML 1.2, then ---         optional, as OpenCV writes them
    name: value                               a number, a string, or a flow list [1, 2, ...] of
                                              numbers (over several lines while its bracket is open)
    name: !!opencv-matrix                     then indented rows: n, cols: n, dt: d, data: [...]
    name: !!opencv-nd-matrix                  then indented sizes: [n] or [n, m], dt: d, data: [...]
    name:                                     then indented `- number` lines

**OpenCV's JSON** (whole-line ``//`` comments allowed, as OpenCV writes them): one object whose
values are numbers, strings, lists of numbers and matrices ``{"type_id": "opencv-matrix", "rows",
"cols", "dt", "data"}`` (``opencv-nd-matrix``: ``sizes`` for rows and cols). Numbers are finite; a
matrix is one channel (``dt`` one of ``ucwsifdh``) of one or two dimensions, its data as many
values as its sizes say. Anything else (other tags, anchors, aliases, block scalars, nested maps,
NaN) is a RigError naming the entry.
"""

from __future__ import annotations

import json
import math
import re
import reprlib
from collections.abc import Iterable

import numpy as np
import yaml

try:
    from yaml import CSafeLoader as _SafeLoader  # libyaml's scanner and parser, PyYAML's safe constructor
except ImportError:  # a PyYAML built without libyaml: the same loader in Python, a few times slower
    from yaml import SafeLoader as _SafeLoader  # type: ignore[assignment]

__all__ = ["MAX_CALIBRATION_BYTES", "MAX_LINES", "RigError", "Value", "parse_entries"]

MAX_CALIBRATION_BYTES = 256 << 10
"""Largest calibration file (a calibration file is a few kilobytes)."""
MAX_LINES = 1000
"""Most lines of a calibration file (one has under a hundred): its cost stays a few milliseconds."""
MAX_NESTING = 16
"""Deepest a ROS camera_info's YAML values may nest (its own nest 3 deep: header.stamp.sec)."""

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
Read = tuple[str | None, dict[str, Value]]
"""A file's form ("opencv", "ros", or None: neither's names) and its entries."""

_OPENCV_NAMES = frozenset({"K1", "D1", "K2", "D2", "T", "image_size"})
"""Top-level names that only an OpenCV calibration has."""
_ROS_ENTRIES = (
    "image_width",
    "image_height",
    "camera_name",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
    "rectification_matrix",
    "projection_matrix",
)
"""A ROS camera_info's entries, as camera_calibration names them."""
_MESSAGE_NAMES = {
    "d": "distortion_coefficients",
    "k": "camera_matrix",
    "r": "rectification_matrix",
    "p": "projection_matrix",
}
"""A CameraInfo message's lists (ROS 2's names; ROS 1's are upper case)."""
_ROS_NAMES = {
    **{name: name for name in _ROS_ENTRIES},
    "width": "image_width",
    "height": "image_height",
    **_MESSAGE_NAMES,  # ROS 2's CameraInfo message
    **{name.upper(): entry for name, entry in _MESSAGE_NAMES.items()},  # ROS 1's
}
"""The entry each name of a ROS camera_info is read as (camera_calibration's YAML, a CameraInfo
message of ROS 2 or ROS 1); its other names (header, binning_x, roi, ...) are not read."""
_SHARED_NAMES = frozenset({"R", "image_width", "image_height"})
"""Top-level names of either form."""
_ROS_ONLY_NAMES = frozenset(_ROS_NAMES) - _SHARED_NAMES
_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
"""ROS's distortion models that are OpenCV's lens model (5 and 8 coefficients)."""
_FORMS = (
    "send one OpenCV calibration file, YAML or JSON as cv2.FileStorage writes it (K1, D1, K2, D2, R, T, "
    "image_width, image_height), or two ROS camera_info files (the left camera's, then the right camera's), YAML "
    "as camera_calibration writes it (image_width, image_height, camera_matrix, distortion_coefficients, "
    "rectification_matrix, projection_matrix) or a CameraInfo message as `ros2 topic echo` prints it (height, "
    "width, distortion_model, d, k, r, p)"
)
_TOP_NAME = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*) *:", re.MULTILINE)
_OPENCV_HEADER = re.compile(r"\A%YAML:1\.[0-2]")


def parse_entries(text: str, source: str, prefix: str = "") -> dict[str, Value]:
    """The top-level entries of a calibration file: an OpenCV calibration's (JSON where the file
    starts with ``{``, else YAML), or a ROS camera_info's (under camera_calibration's names).
    RigError naming ``prefix`` + the entry where one is not of its form, or `source` where the
    file as a whole is not, has no entry (an empty file), is of neither form, or is an OpenCV
    calibration given as a camera_info (`prefix` is a side's: one of a pair of ROS files)."""
    if len(text) > MAX_CALIBRATION_BYTES:
        raise RigError(source, f"larger than {MAX_CALIBRATION_BYTES >> 10} KiB (a calibration is a few kilobytes)")
    if text.count("\n") > MAX_LINES:
        raise RigError(source, f"more than {MAX_LINES} lines (a calibration has under a hundred)")
    read = _json_file_entries if text.lstrip().startswith("{") else _yaml_entries
    form, entries = read(text, source, prefix)
    if not entries:
        raise RigError(source, "the file is empty (no calibration entries)")
    if form is None:
        raise _neither(source, list(entries))
    if prefix and form == "opencv":
        found = ", ".join(name for name in entries if name in _OPENCV_NAMES | _SHARED_NAMES)
        raise RigError(
            source,
            f"an OpenCV calibration ({found}), not a ROS camera_info: send one OpenCV calibration file, or two ROS "
            "camera_info files (the left camera's, then the right camera's)",
        )
    return entries


def _form(names: Iterable[object]) -> str | None:
    """The form of a file by its top-level names: "opencv", "ros", or None where they are neither's."""
    given = set(names)
    if given & _OPENCV_NAMES:
        return "opencv"
    if given & _ROS_ONLY_NAMES:
        return "ros"
    return "opencv" if given & _SHARED_NAMES else None


def _neither(source: str, names: list[object] | None) -> RigError:
    if names is None:
        found = "a YAML value that is not a map of named entries"
    else:
        found = f"its entries are {', '.join(str(name)[:32] for name in names[:6])}{', ...' if len(names) > 6 else ''}"
    return RigError(source, f"neither an OpenCV calibration nor a ROS camera_info ({found}): {_FORMS}")


def _not_read(source: str, problem: str) -> RigError:
    return RigError(source, f"not a YAML or JSON file as OpenCV or ROS write it: {problem}")


# --- which reader ----------------------------------------------------------------------------------


def _json_file_entries(text: str, source: str, prefix: str) -> Read:
    """The entries of a file that starts with ``{``: JSON, OpenCV's or a ROS camera_info's; or, not
    being JSON, a ROS camera_info as a YAML flow map ({k: [...], ...})."""
    try:
        document = _json_document(text, source)
    except RigError as not_json:
        return _yaml_entries(text, source, prefix, not_json)
    form = _form(document)
    if form == "ros":
        return "ros", _ros_entries(document, prefix)
    if form is None and document:
        raise _neither(source, list(document))
    return form, _json_entries(document, source, prefix)


def _yaml_entries(text: str, source: str, prefix: str, not_json: RigError | None = None) -> Read:
    """The entries of a YAML file: composed by PyYAML (nodes, nothing constructed yet) to tell its
    form by its top-level names; a ROS camera_info's then constructed, an OpenCV calibration's read
    by the strict reader. Where PyYAML cannot compose the file, its form is told by the names its
    lines start with: a ROS camera_info's is refused with PyYAML's reason, anything else goes to the
    strict reader, whose reasons name OpenCV's grammar. `not_json`: why a file that starts with ``{``
    is not JSON, raised unless the file is a ROS camera_info. A line that starts with a name only
    OpenCV's calibration has (K1, ...) makes it one without PyYAML: its time stays the strict
    reader's (a few milliseconds for 256 KiB, where PyYAML takes 100)."""
    if not_json is None and not _OPENCV_NAMES.isdisjoint(_TOP_NAME.findall(text)):
        entries = _opencv_yaml_entries(text, source, prefix)
        return _form(entries), entries
    try:
        loader = _Loader(_OPENCV_HEADER.sub("%YAML 1.1", text))  # OpenCV's header is not YAML's
    except yaml.YAMLError as error:  # PyYAML's own reader checks the characters first
        return _not_composed(text, source, prefix, error, not_json)
    try:
        try:
            documents = _documents(loader)
        except (yaml.YAMLError, RecursionError) as error:
            return _not_composed(text, source, prefix, error, not_json)
        root = documents[0] if documents else None
        names: list[object] = []
        if isinstance(root, yaml.MappingNode):
            names = [key.value for key, _ in root.value if isinstance(key, yaml.ScalarNode)]
        form = _form(names)
        if form != "ros" and not_json is not None:
            raise not_json
        if root is None:
            return None, {}
        if not isinstance(root, yaml.MappingNode):
            raise _neither(source, None)
        if form == "opencv" or not names:
            return form, _opencv_yaml_entries(text, source, prefix)
        if form is None:
            raise _neither(source, names)
        if len(documents) > 1:
            raise RigError(
                source,
                f"{len(documents)} YAML documents (--- between them), as `ros2 topic echo` prints {len(documents)} "
                "messages: give one camera_info (`ros2 topic echo --once`)",
            )
        return "ros", _ros_yaml_entries(loader, root, source, prefix)
    finally:
        loader.dispose()


def _not_composed(text: str, source: str, prefix: str, error: Exception, not_json: RigError | None) -> Read:
    """A file PyYAML cannot compose: a ROS camera_info (by the names its lines start with) refused
    with PyYAML's reason; else the strict reader's (OpenCV's) entries, or `not_json`."""
    if _form(_TOP_NAME.findall(text)) == "ros":
        raise _not_read(source, _yaml_problem(error)) from None
    if not_json is not None:
        raise not_json from None
    entries = _opencv_yaml_entries(text, source, prefix)
    return _form(entries), entries


# --- ROS camera_info (PyYAML) ----------------------------------------------------------------------


class _Loader(_SafeLoader):
    """PyYAML's safe loader (plain data only: no Python object is ever made from a file), which also
    reads YAML 1.2's numbers with an exponent and no dot (1e-05, as C++'s yaml-cpp writes them) as
    numbers, not strings."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _documents(loader: _Loader) -> list[yaml.Node]:
    """The file's YAML documents as PyYAML composes them (empty ones left out: `ros2 topic echo`
    ends a message with ---)."""
    documents = []
    while loader.check_node():
        node = loader.get_node()
        if node is not None and not (isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:null"):
            documents.append(node)
    return documents


def _yaml_problem(error: BaseException) -> str:
    if isinstance(error, RecursionError):
        return "nested too deeply"
    if isinstance(error, yaml.MarkedYAMLError):
        problem = ": ".join(part for part in (error.context, error.problem) if part) or str(error)
        mark = error.problem_mark or error.context_mark
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}" if mark is not None else problem
    return str(error)


def _ros_yaml_entries(loader: _Loader, root: yaml.MappingNode, source: str, prefix: str) -> dict[str, Value]:
    """A ROS camera_info's entries from its composed YAML, once it has no alias and no name twice;
    only the entries read are constructed."""
    _check_nodes(root, source, prefix)
    document: dict[str, object] = {}
    for key, node in root.value:
        if isinstance(key, yaml.ScalarNode) and key.value in _ROS_NAMES:
            try:
                document[key.value] = loader.construct_object(node, deep=True)
            except yaml.YAMLError as error:
                raise RigError(prefix + key.value, _yaml_problem(error)) from None
    return _ros_entries(document, prefix)


def _check_nodes(root: yaml.MappingNode, source: str, prefix: str) -> None:
    """RigError naming the entry where a node is met twice (an alias: YAML's *name), a map gives a
    name twice, or values nest deeper than MAX_NESTING (PyYAML constructs them recursively). One
    visit a node: the walk is as long as the file."""
    _unique_names(root, prefix=prefix)
    seen = {id(root)}
    for key, value in root.value:
        field = prefix + key.value if isinstance(key, yaml.ScalarNode) else source
        stack: list[tuple[yaml.Node, int]] = [(key, 1), (value, 1)]
        while stack:
            node, depth = stack.pop()
            if depth > MAX_NESTING:
                raise RigError(field, f"nested more than {MAX_NESTING} deep (a camera_info's entries nest 3 deep)")
            if id(node) in seen:
                raise RigError(
                    field,
                    "holds a YAML alias (*name), which is not read: write the values out (a few nested aliases "
                    "can make a small file read as gigabytes)",
                )
            seen.add(id(node))
            if isinstance(node, yaml.SequenceNode):
                stack.extend((item, depth + 1) for item in node.value)
            elif isinstance(node, yaml.MappingNode):
                _unique_names(node, field)
                stack.extend((part, depth + 1) for pair in node.value for part in pair)


def _unique_names(node: yaml.MappingNode, field: str | None = None, prefix: str = "") -> None:
    """RigError where the map `node` gives a name twice, naming `field` (None: the name itself,
    after `prefix`: a top-level entry)."""
    names: set[str] = set()
    for key, _ in node.value:
        if isinstance(key, yaml.ScalarNode):
            if key.value in names:
                raise RigError(field or prefix + key.value, f"`{key.value}` is given twice")
            names.add(key.value)


def _ros_entries(document: dict[str, object], prefix: str) -> dict[str, Value]:
    """A ROS camera_info's entries under camera_calibration's names (k as camera_matrix, width as
    image_width, ...), each a number, a string or a float64 array; RigError naming the entry as the
    file names it where one is not."""
    entries: dict[str, Value] = {}
    given: dict[str, str] = {}
    for name, value in document.items():
        entry = _ROS_NAMES.get(name)
        if entry is None:
            continue
        if entry in given:
            raise RigError(prefix + name, f"`{given[entry]}` and `{name}` both give the {entry.replace('_', ' ')}")
        given[entry] = name
        entries[entry] = _ros_value(prefix + name, value)
    model = entries.get("distortion_model")
    if model is not None and model not in _DISTORTION_MODELS:
        raise RigError(
            prefix + "distortion_model",
            f"{_shown(model)} is not read: expected {' or '.join(_DISTORTION_MODELS)}, the lens models OpenCV "
            "rectifies with (ROS's equidistant is a fisheye lens's)",
        )
    return entries


def _ros_value(field: str, value: object, in_matrix: bool = False) -> Value:
    """One value of a ROS camera_info as PyYAML or JSON gives it: a number, a string, a list of
    numbers or (not within a matrix) a matrix {rows, cols, data}."""
    if isinstance(value, bool):
        raise RigError(field, f"expected a number, got {value}")
    if isinstance(value, int | float):
        return _ros_number(field, value)
    if isinstance(value, str):
        return value
    if isinstance(value, list):
        for item in value:
            if isinstance(item, bool) or not isinstance(item, int | float):
                raise RigError(field, f"expected a list of numbers [1, 2, ...], got {_shown(item)} in it")
        return np.array([_ros_number(field, item) for item in value], np.float64)
    if isinstance(value, dict) and not in_matrix:
        parts: dict[str, Value] = {str(name): _ros_value(field, part, True) for name, part in value.items()}
        return _matrix(field, "ros", parts)
    if value is None:
        raise RigError(field, "has no value")
    raise RigError(
        field, f"expected a number, a string, a list of numbers or a matrix {{rows, cols, data}}, got {_shown(value)}"
    )


def _ros_number(field: str, value: int | float) -> float:
    try:
        return _finite(field, float(value))
    except OverflowError:  # an integer beyond float64
        raise RigError(field, _NOT_FINITE_REASON) from None


_SHOWN = reprlib.Repr()
_SHOWN.maxstring, _SHOWN.maxother, _SHOWN.maxlist, _SHOWN.maxdict, _SHOWN.maxlevel = 32, 32, 4, 4, 2


def _shown(value: object) -> str:
    """`value` for a message, bounded (a few dozen characters however large it is)."""
    return _SHOWN.repr(value)


# --- OpenCV's YAML ---------------------------------------------------------------------------------


def _opencv_yaml_entries(text: str, source: str, prefix: str) -> dict[str, Value]:
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
    """The indented lines under `name: !!opencv-matrix` (or nd-matrix): the matrix's parts (`name:
    value` lines); under `name:`, a list of numbers (`- number` lines)."""
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
    if items or not tag:
        raise RigError(field, "neither a list of numbers (`- number` lines) nor a matrix (!!opencv-matrix)")
    return _matrix(field, tag.removeprefix("!!"), parts)


def _value(field: str, text: str) -> Value:
    """One value on a line: a number, a flow list of numbers, or a string."""
    if text.startswith("["):
        return _list(field, text)
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


def _json_document(text: str, source: str) -> dict[str, object]:
    """The object of a JSON file (numbers as floats; no NaN, no name twice)."""
    lines = ("" if line.lstrip().startswith("//") else line for line in text.split("\n"))  # OpenCV's comments
    try:
        document = json.loads("\n".join(lines), parse_int=float, parse_constant=_no_constant, object_pairs_hook=_unique)
    except (ValueError, RecursionError) as error:
        raise _not_read(source, str(error)) from None
    if not isinstance(document, dict):
        raise _not_read(source, "a JSON calibration is one object")
    return document


def _json_entries(document: dict[str, object], source: str, prefix: str) -> dict[str, Value]:
    """An OpenCV calibration's entries from its JSON object."""
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
