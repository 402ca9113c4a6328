"""Command-line options from frozen dataclass configs: one option per field, its doc the help.

A config declares each field with ``option(default, doc)``; the doc lives in the field's
metadata, so ``--help`` needs no source code, and ``add_options`` turns every plain field
(``int``, ``float``, ``str``, ``X | None``, or ``tuple[str, ...]`` for a list of names) into
``--field-name``; an ``X | None`` option takes ``auto`` for None (its default shown as
``auto``). Nested configs (a field whose default is a dataclass) are not options.

    @dataclass(frozen=True)
    class Config:
        seeds: int = option(100, "Independent experiments per cell.")
        worlds: tuple[str, ...] = option(REGIMES, "Worlds to run (comma-separated).")

    add_options(parser, Config)              # --seeds SEEDS, --worlds NAME[,NAME] (repeatable)
    Config(**given_options(parser.parse_args(argv), Config))   # only what was given

Options that are not given stay out of the namespace (``argparse.SUPPRESS``), so the config's
own defaults apply and a resumed run can tell given options from defaults.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import types
import typing
from typing import Any

#: The placeholder of a list option's value.
NAMES_METAVAR = "NAME[,NAME]"


def finite_float(text: str) -> float:
    """argparse's type of every float option: a finite number. ``inf``, ``nan`` and anything past
    the float range (``1e400``, a 400-digit integer: both read as ``inf``) are refused while the
    options are parsed, in one line, before any work (a config's own range checks follow)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


#: What an ``X | None`` option takes for None: its help shows ``(default: auto)``.
AUTO = "auto"


def _or_auto(kind: Any) -> Any:
    """argparse's type of an ``X | None`` option: ``auto`` is None, anything else ``kind``'s
    (its name kept, so argparse's message still reads "invalid int value")."""

    def parse(text: str) -> Any:
        return None if text == AUTO else kind(text)

    parse.__name__ = getattr(kind, "__name__", "value")
    return parse


def option(default: Any, doc: str, *, choices: tuple[str, ...] | None = None) -> Any:
    """A dataclass field with its one-line ``doc`` (the ``--help`` text) and, for a string
    option, the ``choices`` argparse offers."""
    metadata = {"doc": doc} if choices is None else {"doc": doc, "choices": tuple(choices)}
    return dataclasses.field(default=default, metadata=metadata)


def check_choices(config: Any) -> None:
    """Refuse (a ValueError naming it) a field of dataclass ``config`` declared with ``choices``
    whose value is not one of them: what argparse checks of an option, checked of a config made
    in code too."""
    for field in dataclasses.fields(config):
        choices, value = field.metadata.get("choices"), getattr(config, field.name)
        if choices is not None and value not in choices:
            raise ValueError(
                f"{field.name}={value!r} is unknown: choose one of {', '.join(choices)}"
            )


def option_name(name: str) -> str:
    """``max_steps`` -> ``--max-steps``."""
    return "--" + name.replace("_", "-")


def _is_names(annotation: Any) -> bool:
    return typing.get_origin(annotation) is tuple and typing.get_args(annotation) == (str, ...)


def _value_type(annotation: Any) -> type | None:
    """``int``, ``float`` or ``str`` from a field's annotation (``int | None`` -> ``int``);
    ``None`` for anything else (a nested config, a tuple of numbers)."""
    if isinstance(annotation, types.UnionType):
        annotation = next(arg for arg in typing.get_args(annotation) if arg is not type(None))
    return annotation if annotation in (int, float, str) else None


def option_fields(cls: type) -> list[dataclasses.Field]:
    """The fields of ``cls`` that are command-line options, in declaration order."""
    hints = typing.get_type_hints(cls)
    return [
        f
        for f in dataclasses.fields(cls)
        if _is_names(hints[f.name]) or _value_type(hints[f.name]) is not None
    ]


def add_options(parser: argparse.ArgumentParser, cls: type) -> None:
    """One option per plain field of ``cls``, its help the field's doc and default."""
    hints = typing.get_type_hints(cls)
    for field in option_fields(cls):
        default = field.default
        doc = field.metadata.get("doc", "")
        if _is_names(hints[field.name]):
            shown = ",".join(default) if isinstance(default, tuple) else default
            help_text = f"{doc} Repeatable. (default: {shown})"
            kwargs: dict[str, Any] = {"action": "append", "metavar": NAMES_METAVAR}
        else:
            help_text = f"{doc} (default: {AUTO if default is None else default})"
            kind = _value_type(hints[field.name])
            parse: Any = finite_float if kind is float else kind
            if isinstance(hints[field.name], types.UnionType):  # X | None: "auto" gives None
                parse = _or_auto(parse)
            kwargs = {"type": parse, "metavar": field.name.upper()}
            if "choices" in field.metadata:
                kwargs["choices"] = field.metadata["choices"]
        parser.add_argument(
            option_name(field.name),
            help=help_text.replace("%", "%%"),  # argparse %-formats help texts
            default=argparse.SUPPRESS,
            **kwargs,
        )


def given_options(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The fields of ``cls`` given on the command line (name -> value); a list option's values
    may be repeated and/or comma-separated."""
    hints = typing.get_type_hints(cls)
    values = {}
    for field in option_fields(cls):
        if hasattr(args, field.name):
            value = getattr(args, field.name)
            if _is_names(hints[field.name]):
                value = [item for given in value for item in given.split(",")]
            values[field.name] = value
    return values
