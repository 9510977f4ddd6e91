"""The `ds3d` parser. Each area module listed in COMMAND_MODULES has `register(commands, evals,
benches)`, where the three arguments are argparse sub-parser collections for `ds3d <cmd>`,
`ds3d eval <what>` and `ds3d bench <what>`; every parser it adds sets
`func=callable(args) -> int | None`. Shared here, each defined once: the model options
(--model-dir, --database, --device, --threads, --workers), `--set NAME=VALUE` overrides of a
dataclass's fields, the people options, the pipeline they load, and JSON reports.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import sys
import typing
from pathlib import Path

import torch

from ds3d.inputs import MIN_SCORE
from ds3d.util.machine import default_threads, default_workers
from ds3d.util.paths import MODELS_DIR
from ds3d.util.progress import set_quiet
from ds3d.util.provenance import provenance

COMMAND_MODULES: tuple[str, ...] = (
    "ds3d.cli.data",
    "ds3d.cli.lift",
    "ds3d.cli.image2d",
    "ds3d.cli.predict",
    "ds3d.cli.pipeline",
    "ds3d.cli.ray_data",
    "ds3d.cli.bench",
)
DEFAULT_IMAGE2D = MODELS_DIR / "image2d"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ds3d", description="The `ds3d` command line: 3D human pose from a single image."
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bars (shown only on a terminal anyway)"
    )
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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    set_quiet(args.quiet)
    return int(args.func(args) or 0)


def add_model_options(parser, threads: int | None = 1, device: bool = False) -> None:
    """--model-dir (holds image2d/ and the pose databases), --database, --threads (default
    `threads`; None: torch's default) and, with `device`, --device (add_device_option)."""
    parser.add_argument(
        "--model-dir", type=Path, default=MODELS_DIR, help="holds image2d/, posedb/"
    )
    parser.add_argument("--database", default="posedb", help="pose database folder in --model-dir")
    if device:
        add_device_option(parser)
    parser.add_argument("--threads", type=int, default=threads, help="torch CPU threads")


def add_device_option(parser, help: str = "where the models run") -> None:
    """--device: cpu or cuda, by default cuda where torch sees a GPU."""
    default = "cuda" if torch.cuda.is_available() else "cpu"
    parser.add_argument("--device", choices=("cpu", "cuda"), default=default, help=help)


def add_workers_option(parser) -> None:
    """--workers: processes that split each batch (ds3d.runners.workers); by default, and with
    --threads, sized from the machine (resolve_workers)."""
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes, each its own models with --threads torch threads, that split each "
        "batch (more images/s than as many threads on a CPU; about 0.8 GB each); default: one "
        "per usable core, as many as the memory holds, 1 on a GPU (ds3d.util.machine)",
    )


def resolve_workers(args) -> None:
    """A command's --workers and --threads left unset, sized from the machine: workers
    default_workers(--device), threads the cores shared among them (default_threads)."""
    if args.workers is None:
        args.workers = default_workers(getattr(args, "device", "cpu"))
    if args.threads is None:
        args.threads = default_threads(args.workers)


def set_threads(args) -> None:
    """torch's CPU threads from --threads, when given."""
    if args.threads:
        torch.set_num_threads(args.threads)


def load_pipeline(args, config=None):
    """The Pipeline of --model-dir and --database, on --device where the command has it (else
    the CPU), on --threads torch threads, with `config` (a PipelineConfig; None: the default);
    with --workers N > 1, a PipelineWorkers of N such pipelines (ds3d.runners.workers), whose
    estimate() and run() are the Pipeline's."""
    from ds3d.pipeline import Pipeline, PipelineConfig
    from ds3d.runners.workers import PipelineWorkers

    config = config or PipelineConfig()
    device = getattr(args, "device", "cpu")
    load = {"model_dir": args.model_dir, "device": device, "database": args.database}
    if hasattr(args, "workers"):
        resolve_workers(args)
    if getattr(args, "workers", 1) > 1:
        return PipelineWorkers(args.workers, args.threads or 1, config=config, **load)
    set_threads(args)
    return Pipeline.load(config=config, **load)


def add_people_options(parser) -> None:
    """--people (best or all) and --min-score, of the commands that estimate people in images."""
    parser.add_argument(
        "--people",
        choices=("best", "all"),
        default="best",
        help="best: the likeliest person per image; all: every person found",
    )
    parser.add_argument(
        "--min-score", type=float, default=MIN_SCORE, help="people scoring less are not answered"
    )


def add_set_option(parser, text: str) -> None:
    """--set NAME=VALUE, repeatable: overrides of a dataclass's fields (field_overrides)."""
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help=text)


def field_overrides(cls, items: list[str]) -> dict:
    """`--set NAME=VALUE` items -> {field: value} for the dataclass `cls`, each value converted
    to the field's annotated type (bools from true/false/1/0; `none` for optional fields).
    `NAME.FIELD=VALUE` sets a field of a nested dataclass (e.g. `omega.proportions=20`), the
    others keeping cls()'s values. Exits with a message on an unknown field or a value that
    does not convert."""
    types = typing.get_type_hints(cls)
    out: dict = {}
    nested: dict[str, list[str]] = {}
    for item in items:
        key, _, value = item.partition("=")
        outer, dot, inner = key.partition(".")
        if dot and dataclasses.is_dataclass(types.get(outer)):
            nested.setdefault(outer, []).append(f"{inner}={value}")
            continue
        if key not in types:
            raise SystemExit(f"--set {item}: not a {cls.__name__} field ({', '.join(types)})")
        try:
            out[key] = _convert(types[key], value)
        except ValueError:
            name = getattr(types[key], "__name__", str(types[key]))
            raise SystemExit(f"--set {item}: {value!r} is not a {name}") from None
    for outer, inner_items in nested.items():
        default = getattr(cls(), outer)
        out[outer] = dataclasses.replace(default, **field_overrides(type(default), inner_items))
    return out


def _convert(kind, value: str):
    """A --set value as `kind`: bool, int, float, str, an optional (`X | None`) of them, or a
    tuple of them, comma-separated (`64,128,192`)."""
    options = typing.get_args(kind)
    if type(None) in options:
        if value.lower() == "none":
            return None
        (kind,) = (o for o in options if o is not type(None))
    if typing.get_origin(kind) is tuple:
        items = value.split(",")
        kinds = typing.get_args(kind)
        kinds = kinds[:1] * len(items) if kinds[-1:] == (Ellipsis,) else kinds
        if len(kinds) != len(items):
            raise ValueError(value)
        return tuple(_convert(k, item) for k, item in zip(kinds, items, strict=True))
    if kind is bool:
        if value.lower() not in ("true", "false", "1", "0"):
            raise ValueError(value)
        return value.lower() in ("true", "1")
    return kind(value)


def write_report(report: dict, out: Path | None) -> None:
    """A command's JSON report, with its provenance (commit, machine, date, command:
    ds3d.util.provenance): to `out` (folders created) when given, else to stdout."""
    text = json.dumps({**report, "provenance": provenance()}, indent=2)
    if out is None:
        print(text)
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text + "\n")
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
