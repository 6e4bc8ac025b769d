"""Command-line options generated from a dataclass's typed fields (one `--field-name` each).

Only the options given on the command line are returned, so that they override a base config
(a preset, or the config of a checkpoint being resumed) and nothing else does.
"""

from __future__ import annotations

import argparse
import types
import typing
from dataclasses import fields
from typing import Any, Literal

from crestereo_pp.training.config import DataSource

_SINGULAR = {"sources": "source"}
"""Tuple-valued fields spelled singular on the command line (`--source A --source B`)."""


def option_name(field_name: str) -> str:
    return "--" + _SINGULAR.get(field_name, field_name).replace("_", "-")


def add_dataclass_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls: type) -> None:
    """Add one option per field of dataclass `cls`, typed from its annotation, helped from its
    metadata["help"], defaulting to "not given" (the dataclass default is shown in the help)."""
    hints = typing.get_type_hints(cls)
    for f in fields(cls):
        kind = strip_optional(hints[f.name])
        options: dict[str, Any] = {
            "dest": f.name,
            "default": argparse.SUPPRESS,
            "help": f"{f.metadata['help']} [{_show(f.default)}]",
        }
        origin, arguments = typing.get_origin(kind), typing.get_args(kind)
        if kind is bool:
            options["action"] = argparse.BooleanOptionalAction
        elif origin is Literal:
            options.update(choices=arguments, type=type(arguments[0]))
        elif origin is tuple and arguments[-1] is Ellipsis:
            options.update(action="append", type=_parser(arguments[0]), metavar=f.metadata.get("metavar"))
        elif origin is tuple:
            options.update(nargs=len(arguments), type=_parser(arguments[0]))
        elif kind in (int, float, str):
            options["type"] = kind
        else:
            raise TypeError(f"no command-line form for field {f.name}: {kind}")
        parser.add_argument(option_name(f.name), **options)


def given_options(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The fields of `cls` given on the command line, as values of their annotated types."""
    values = {}
    for f in fields(cls):
        if hasattr(args, f.name):
            value = getattr(args, f.name)
            values[f.name] = tuple(value) if isinstance(value, list) else value
    return values


def strip_optional(kind: Any) -> Any:
    """X for `X | None`, else the type unchanged."""
    arguments = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, types.UnionType) and type(None) in arguments:
        (inner,) = [a for a in arguments if a is not type(None)]
        return inner
    return kind


def _parser(kind: type) -> Any:
    """Parser of one element of a tuple-valued option."""
    return DataSource.parse if kind is DataSource else kind


def _show(default: Any) -> str:
    if isinstance(default, tuple):
        return " ".join(str(v) for v in default)
    return str(default)
