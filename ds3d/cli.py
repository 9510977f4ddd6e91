"""The `ds3d` command line. Each part of the library registers its own subcommands:
a module listed in COMMAND_MODULES has `register(commands, evals, benches)`, where the three
arguments are argparse sub-parser collections for `ds3d <cmd>`, `ds3d eval <what>` and
`ds3d bench <what>`; every parser it adds sets `func=callable(args) -> int | None`.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import typing
from pathlib import Path

COMMAND_MODULES: tuple[str, ...] = (
    "ds3d.lift_commands",
    "ds3d.image2d.commands",
    "ds3d.pipeline_commands",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ds3d", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    evals = commands.add_parser("eval", help="evaluate on a dataset protocol").add_subparsers(
        dest="what", required=True
    )
    benches = commands.add_parser("bench", help="measure speed").add_subparsers(
        dest="what", required=True
    )
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(commands, evals, benches)
    return parser


def field_overrides(cls, items: list[str]) -> dict:
    """`--set NAME=VALUE` items -> {field: value} for the dataclass `cls`, each value converted
    to the field's annotated type (bools from true/false/1/0; `none` for optional fields).
    Exits with a message on an unknown field or a value that does not convert."""
    types = typing.get_type_hints(cls)
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in types:
            raise SystemExit(f"--set {item}: not a {cls.__name__} field ({', '.join(types)})")
        try:
            out[key] = _convert(types[key], value)
        except ValueError:
            name = getattr(types[key], "__name__", str(types[key]))
            raise SystemExit(f"--set {item}: {value!r} is not a {name}") from None
    return out


def _convert(kind, value: str):
    """A --set value as `kind`: bool, int, float, str or an optional (`X | None`) of them."""
    options = typing.get_args(kind)
    if type(None) in options:
        if value.lower() == "none":
            return None
        (kind,) = (o for o in options if o is not type(None))
    if kind is bool:
        if value.lower() not in ("true", "false", "1", "0"):
            raise ValueError(value)
        return value.lower() in ("true", "1")
    return kind(value)


def write_report(report: dict, out: Path | None) -> None:
    """A command's JSON report: to `out` (folders created) when given, else to stdout."""
    text = json.dumps(report, indent=2)
    if out is None:
        print(text)
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n")
    print(f"wrote {out}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
