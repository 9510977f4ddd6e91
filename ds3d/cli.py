"""The `ds3d` command line. Each part of the library registers its own subcommands:
a module listed in COMMAND_MODULES has `register(commands, evals, benches)`, where the three
arguments are argparse sub-parser collections for `ds3d <cmd>`, `ds3d eval <what>` and
`ds3d bench <what>`; every parser it adds sets `func=callable(args) -> int | None`.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import sys
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
    to the type of the field's default (bools from true/false/1/0). Exits with a message on an
    unknown field or a value that does not convert."""
    types = {f.name: type(f.default) for f in dataclasses.fields(cls)}
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in types:
            raise SystemExit(f"--set {item}: not a {cls.__name__} field ({', '.join(types)})")
        kind = types[key]
        try:
            if kind is bool:
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(value)
                out[key] = value.lower() in ("true", "1")
            else:
                out[key] = kind(value)
        except ValueError:
            raise SystemExit(f"--set {item}: {value!r} is not a {kind.__name__}") from None
    return out


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
