"""`ds3d batch`: the pipeline over many images on a Ray Data actor pool
(ds3d.runners.ray_data). Ray, an optional extra, is imported only when the command runs."""

from __future__ import annotations

import os
import sys
from pathlib import Path

from ds3d.cli.parser import add_device_option, add_model_options, add_people_options


def register(commands, evals, benches) -> None:
    p = commands.add_parser(
        "batch",
        help="2D and 3D poses of many images with Ray Data: resumable, bad files recorded",
        description="Writes OUT/predictions.jsonl (a line per image, as `ds3d predict`, in the "
        "order they finish) and OUT/errors.jsonl (a line per image that could not be read). A "
        "re-run skips the images already in either. Needs the `ray` extra.",
    )
    p.add_argument(
        "sources",
        nargs="+",
        help="folders (every image below, found by content), globs, image files, or list "
        "files (a text file of image paths, one a line, relative to the current folder)",
    )
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument(
        "--actors",
        default=None,
        help="N: a pool of N actors (each loads the models once); MIN,MAX: a pool Ray grows "
        "(default: this machine's CPU count / --threads)",
    )
    p.add_argument("--batch-size", type=int, default=8, help="images an actor estimates at once")
    add_people_options(p)
    p.add_argument("--iterations", type=int, default=None, help="default: 1 (the paper's: 2)")
    p.add_argument(
        "--max-pixels",
        type=int,
        default=None,
        help="larger images are errors, refused before decoding (default: ds3d.io.images's)",
    )
    p.add_argument(
        "--retry-errors",
        action="store_true",
        help="also re-run the images in OUT/errors.jsonl (their old lines stay)",
    )
    add_device_option(
        p, "where each actor runs the joint network and the 3D stage (cuda: a GPU per actor)"
    )
    p.add_argument(
        "--address",
        default=None,
        help="a Ray cluster to run on (default: $RAY_ADDRESS, else a local Ray for the run)",
    )
    add_model_options(p, threads=1)  # --threads: torch threads (and CPUs) per actor
    p.set_defaults(func=batch)


def batch(args) -> int:
    from ds3d.runners.ray_data import (
        RAY_MISSING,
        BatchOptions,
        ResultWriter,
        done_sources,
        list_images,
        parse_actors,
        run_batch,
    )

    try:
        import ray  # noqa: F401  (only to say early, and clearly, that it is missing)
    except ImportError:
        raise SystemExit(RAY_MISSING) from None
    from ds3d.io.images import DEFAULT_MAX_PIXELS

    try:
        default = max(1, (os.cpu_count() or 2) // max(1, args.threads))
        actors = parse_actors(args.actors or str(default))
    except ValueError as err:
        raise SystemExit(f"--actors: {err}") from None
    paths, listing_errors = list_images(args.sources)
    done = done_sources(args.out, retry_errors=args.retry_errors)
    todo = [p for p in paths if p not in done]
    new_errors = [e for e in listing_errors if e["source"] not in done]
    skipped = len(paths) - len(todo)
    print(f"{len(paths)} images: {skipped} already done, {len(todo)} to do", file=sys.stderr)
    options = BatchOptions(
        people=args.people,
        min_score=args.min_score,
        iterations=args.iterations,
        max_pixels=DEFAULT_MAX_PIXELS if args.max_pixels is None else args.max_pixels,
    )
    quiet = args.quiet or not sys.stderr.isatty()
    with ResultWriter(args.out) as writer:
        writer.add_errors(new_errors)
        if todo:
            try:
                run_batch(
                    todo,
                    writer,
                    model_dir=args.model_dir,
                    database=args.database,
                    device=args.device,
                    actors=actors,
                    batch_size=args.batch_size,
                    threads=args.threads,
                    options=options,
                    quiet=quiet,
                    address=args.address,
                )
            except KeyboardInterrupt:
                print("interrupted: a re-run goes on from here", file=sys.stderr)
    print(
        f"{writer.written} estimated, {writer.failed} errors, {skipped} skipped as done: "
        f"wrote {args.out}/",
        file=sys.stderr,
    )
    return 0
