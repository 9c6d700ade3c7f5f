"""Command lines from typed configs: one frozen dataclass per command is the single source of
its options, defaults and ``--help``.

Each field becomes an option ``--field-name`` (or a positional argument), typed by its
annotation: ``int``, ``float``, ``str``, ``bool`` (``--x`` / ``--no-x``), ``X | None``,
``tuple[X, ...]`` (one or more values). Its help text is the field's entry in the class
docstring's ``Attributes:`` section (so the docstring and ``--help`` cannot disagree), and
``option(...)`` in the field's metadata adds what a type cannot say: positional, choices (a
callable is evaluated when the parser is built, e.g. the registered policy names), ``nargs``,
``const``, ``metavar``::

    @dataclass(frozen=True, kw_only=True)
    class Render:
        \"\"\"Simulate one scenario and write a video.

        Attributes:
            file: a TFRecord or JSON scenario file.
            fps: video frames per second.
        \"\"\"

        file: str = field(metadata=option(positional=True))
        fps: int = 10

    parser = config_parser(Render)
    cfg = parse_config(Render, parser.parse_args(["x.tfrecord", "--fps", "20"]))
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import types
import typing
from collections.abc import Callable, Sequence
from typing import Any

OPTION_KEY = "cli"


def option(
    *,
    positional: bool = False,
    choices: Sequence[str] | Callable[[], Sequence[str]] | None = None,
    nargs: str | None = None,
    const: Any = None,
    metavar: str | None = None,
) -> dict[str, Any]:
    """Field metadata for ``add_config_arguments`` (see the module docstring)."""
    return {
        OPTION_KEY: {
            "positional": positional,
            "choices": choices,
            "nargs": nargs,
            "const": const,
            "metavar": metavar,
        }
    }


def attribute_help(cls: type) -> dict[str, str]:
    """``{field: text}`` from the ``Attributes:`` section of a class docstring (continuation
    lines indented deeper are joined)."""
    out: dict[str, str] = {}
    doc = inspect.getdoc(cls) or ""
    if "Attributes:" not in doc:
        return out
    name = None
    for line in doc.split("Attributes:", 1)[1].splitlines():
        head, sep, text = line.strip().partition(": ")
        if line.startswith("    ") and not line.startswith("     ") and sep and head.isidentifier():
            name, out[head] = head, text
        elif name and line.startswith("     "):
            out[name] += " " + line.strip()
        elif line.strip():
            name = None
    return out


def _unwrap(hint: Any) -> tuple[Any, bool, bool]:
    """(scalar type, optional, sequence) of a field annotation."""
    optional = False
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional, hint = True, args[0]
    if typing.get_origin(hint) in (tuple, list):
        return typing.get_args(hint)[0], optional, True
    return hint, optional, False


def _argument(field: dataclasses.Field, hint: Any, text: str) -> tuple[list[str], dict]:
    """(names, keyword arguments) of ``parser.add_argument`` for one field."""
    spec = field.metadata.get(OPTION_KEY, {})
    kind, _, many = _unwrap(hint)
    required = field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING
    default = None if required else field.default
    if field.default_factory is not dataclasses.MISSING:
        default = field.default_factory()
    kw: dict[str, Any] = {"help": text.replace("%", "%%")}
    if not required and default is not None and default is not False and default != ():
        kw["help"] += " (default: %(default)s)"
    choices = spec.get("choices")
    if choices is not None:
        kw["choices"] = tuple(choices() if callable(choices) else choices)
    for key in ("nargs", "const", "metavar"):
        if spec.get(key) is not None:
            kw[key] = spec[key]
    if kind is bool:
        kw.update(action=argparse.BooleanOptionalAction, default=default)
    else:
        kw.update(type=kind)
        if many:
            kw.setdefault("nargs", "+" if required else "*")
    if spec.get("positional"):
        if not required:
            kw.setdefault("nargs", "?")
            kw["default"] = default
        return [field.name], kw
    if required:
        kw["required"] = True
    elif kind is not bool:
        kw["default"] = default
    return ["--" + field.name.replace("_", "-")], kw


def add_config_arguments(parser: argparse.ArgumentParser, cls: type) -> None:
    """One argument of ``parser`` per field of the dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    docs: dict[str, str] = {}
    for base in reversed(cls.__mro__):  # a field documented by the class that declares it
        docs.update(attribute_help(base))
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        names, kw = _argument(f, hints[f.name], docs.get(f.name, ""))
        if names[0].startswith("-"):
            parser.add_argument(*names, dest=f.name, **kw)
        else:  # a positional argument's name is its destination
            parser.add_argument(*names, **kw)


def parse_config(cls: type, namespace: argparse.Namespace) -> Any:
    """An instance of ``cls`` from a namespace its arguments were parsed into (sequences as
    tuples)."""
    values = {}
    for f in dataclasses.fields(cls):
        if f.init and hasattr(namespace, f.name):
            v = getattr(namespace, f.name)
            values[f.name] = tuple(v) if isinstance(v, list) else v
    return cls(**values)


def summary(cls: type) -> str:
    """The first line of a class docstring (a command's one-line help)."""
    return (inspect.getdoc(cls) or "").split("\n", 1)[0]


def config_parser(cls: type, prog: str | None = None) -> argparse.ArgumentParser:
    """A parser for one config (a single-command script)."""
    parser = argparse.ArgumentParser(prog=prog, description=summary(cls))
    add_config_arguments(parser, cls)
    return parser


__all__ = [
    "add_config_arguments",
    "attribute_help",
    "config_parser",
    "option",
    "parse_config",
    "summary",
]
