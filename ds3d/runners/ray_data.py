"""`ds3d batch`: the pipeline over many still images with Ray Data, resumable.

    ds3d batch photos/ 'more/**/*.jpg' paths.txt --out results/

writes into the output folder

    predictions.jsonl  a line per image, the record of `ds3d predict` (Prediction.to_dict):
                       source (the image's absolute path), frame (null), width, height, people
    errors.jsonl       a line {"source", "error"} per image that could not be read or estimated
                       (missing, not an image, truncated, more than max_pixels pixels)

in the order the images finish, not the order given. Both files are appended to: a re-run skips
every image already in either (by its absolute path; retry_errors: only those in
predictions.jsonl), so an interrupted run goes on where it stopped.

How it runs: the driver lists the images (list_images) and leaves out those done (done_sources);
Ray Data spreads the remaining paths over a pool of actors (Estimator, one CPU and `threads` torch
threads each, the models loaded once in __init__), each reading, decoding (ds3d.io.images, its
size guards) and estimating a batch at a time (estimate_paths); the driver appends each batch's
lines as it comes (ResultWriter). Files are read by the actors, not by Ray's readers, so that one
unreadable file is one error line, never a failed job.

Ray is an optional extra (pip install -e '.[ray]'): only run_batch imports it.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

from ds3d.errors import InvalidImage
from ds3d.inputs import MIN_SCORE
from ds3d.io.images import DEFAULT_MAX_PIXELS
from ds3d.io.sources import resolve, sniff

PREDICTIONS = "predictions.jsonl"
ERRORS = "errors.jsonl"
RAY_MISSING = "ds3d batch needs Ray, an optional extra: pip install -e '.[ray]'"


@dataclass(frozen=True)
class BatchOptions:
    """What each image is estimated with (as Pipeline.estimate) and the decoder's pixel limit."""

    people: str = "best"
    min_score: float = MIN_SCORE
    iterations: int | None = None
    max_pixels: int = DEFAULT_MAX_PIXELS


def read_list_file(path: str | os.PathLike) -> list[str]:
    """The image paths of a list file: one a line, blank lines and `#` comments skipped;
    relative paths are taken from the current folder (as the shell that wrote them)."""
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    return [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]


def _is_list_file(path: Path) -> bool:
    """An existing file that is neither an image nor a video by content, and is UTF-8 text."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    if sniff(head[:16]) is not None or b"\x00" in head:
        return False
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as err:  # a multi-byte character cut at the end is still text
        return err.start >= len(head) - 3
    return True


def list_images(sources: Iterable[str | os.PathLike]) -> tuple[list[str], list[dict]]:
    """The still images of `sources`, as absolute paths in order without repeats, and an error
    record {"source", "error"} per source that names none. A source is a folder (every image
    below it, found by content, as ds3d.io.sources.resolve), a glob, an image file, or a list file
    (read_list_file: its paths are taken as they are, checked only when read). Videos, cameras
    and URLs are errors here: `ds3d predict` reads them."""
    paths: list[str] = []
    errors: list[dict] = []
    for source in sources:
        text = str(source)
        if Path(text).is_file() and _is_list_file(Path(text)):
            paths += [os.path.abspath(p) for p in read_list_file(text)]
            continue
        for found in resolve([text]):
            if found.kind == "image":
                paths.append(os.path.abspath(found.location))
            elif found.kind == "error":
                errors.append({"source": found.location, "error": found.error})
            else:
                error = f"a {found.kind}: ds3d batch reads still images (ds3d predict reads these)"
                errors.append({"source": found.location, "error": error})
    return list(dict.fromkeys(paths)), errors


def _sources_of(path: Path) -> list[str]:
    """The "source" of every complete line of a JSON Lines file (none if it is missing). A last
    line without its newline, left by an interrupted run, is cut off the file."""
    if not path.is_file():
        return []
    with open(path, "r+b") as f:
        data = f.read()
        end = data.rfind(b"\n") + 1
        if end < len(data):
            f.truncate(end)
    sources = []
    for line in data[:end].splitlines():
        if line.strip():
            try:
                sources.append(json.loads(line)["source"])
            except (ValueError, KeyError, TypeError):
                continue  # not one of ours: left as it is
    return sources


def done_sources(folder: str | os.PathLike, retry_errors: bool = False) -> set[str]:
    """The images a run into `folder` has already answered: those in predictions.jsonl and,
    unless retry_errors, those in errors.jsonl."""
    folder = Path(folder)
    done = set(_sources_of(folder / PREDICTIONS))
    errors = _sources_of(folder / ERRORS)
    return done if retry_errors else done | set(errors)


def estimate_paths(pipeline, paths: Iterable[str], options: BatchOptions) -> dict[str, list[str]]:
    """Reads, decodes and estimates the images `paths` as one batch. Returns the columns
    "source", "record" (the JSON line of predictions.jsonl, "" on an error) and "error"
    ("" when estimated). An image that cannot be read, decoded or searched (ds3d.inputs.
    image_input) is an error; should the batch's estimate fail, its images are estimated one at
    a time, the failing ones errors."""
    from ds3d.inputs import image_input
    from ds3d.io.images import decode_image
    from ds3d.io.prediction import Prediction
    from ds3d.io.sources import Frame

    out: dict[str, list[str]] = {"source": [], "record": [], "error": []}

    def add(source: str, record: str = "", error: str = "") -> None:
        out["source"].append(source)
        out["record"].append(record)
        out["error"].append(error)

    frames, inputs = [], []
    for path in paths:
        path = str(path)
        try:
            with open(path, "rb") as f:
                image = decode_image(f.read(), options.max_pixels)
            inputs.append(image_input(image, people=options.people, min_score=options.min_score))
            frames.append(Frame(path, image=image))
        except (InvalidImage, OSError) as err:
            add(path, error=str(err) if isinstance(err, InvalidImage) else f"cannot read: {err}")

    def estimate(rows: range | list[int]) -> None:
        part = [frames[i] for i in rows]
        result = pipeline.run([inputs[i] for i in rows], options.iterations)
        records = [Prediction(f, result.people(i)).to_dict() for i, f in enumerate(part)]
        for frame, record in zip(part, records, strict=True):
            add(frame.source, record=json.dumps(record))

    if frames:
        try:
            estimate(range(len(frames)))
        except Exception:  # one bad image must not cost the batch: each on its own
            for i, frame in enumerate(frames):
                try:
                    estimate([i])
                except Exception as err:
                    add(frame.source, error=f"estimate failed: {type(err).__name__}: {err}")
    return out


class Estimator:
    """Ray Data's callable class: the pipeline of `model_dir` loaded once per actor, each batch
    {"path": paths} answered by estimate_paths."""

    def __init__(
        self,
        model_dir: str,
        database: str = "posedb",
        device: str = "cpu",
        options: dict | None = None,
        threads: int = 1,
    ):
        import torch

        from ds3d.pipeline import Pipeline

        torch.set_num_threads(threads)
        self.pipeline = Pipeline.load(model_dir, device=device, database=database)
        self.options = BatchOptions(**(options or {}))

    def __call__(self, batch: dict) -> dict:
        import numpy as np

        columns = estimate_paths(self.pipeline, batch["path"].tolist(), self.options)
        return {name: np.array(values, dtype=object) for name, values in columns.items()}


class ResultWriter:
    """Appends result batches to the folder's predictions.jsonl and errors.jsonl, flushed after
    each, so that what is written is kept whenever the run stops."""

    def __init__(self, folder: str | os.PathLike):
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        self.predictions = open(folder / PREDICTIONS, "a", encoding="utf-8")
        self.errors = open(folder / ERRORS, "a", encoding="utf-8")
        self.written = 0
        self.failed = 0

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def add_errors(self, records: Iterable[dict]) -> None:
        for record in records:
            self.errors.write(json.dumps(record) + "\n")
            self.failed += 1
        self.errors.flush()

    def add(self, batch: dict) -> None:
        """A batch of estimate_paths's columns."""
        for source, record, error in zip(
            batch["source"], batch["record"], batch["error"], strict=True
        ):
            if error:
                self.errors.write(json.dumps({"source": str(source), "error": str(error)}) + "\n")
                self.failed += 1
            else:
                self.predictions.write(str(record) + "\n")
                self.written += 1
        self.predictions.flush()
        self.errors.flush()

    def close(self) -> None:
        self.predictions.close()
        self.errors.close()


def parse_actors(text: str) -> int | tuple[int, int]:
    """--actors: "N" (a pool of N) or "MIN,MAX" (a pool Ray grows from MIN to MAX)."""
    try:
        numbers = tuple(int(v) for v in text.split(","))
    except ValueError:
        numbers = ()
    if len(numbers) == 1 and numbers[0] >= 1:
        return numbers[0]
    if len(numbers) == 2 and 1 <= numbers[0] <= numbers[1]:
        return numbers
    raise ValueError(f"actors must be N or MIN,MAX with 1 <= MIN <= MAX, got {text!r}")


def run_batch(
    paths: list[str],
    writer: ResultWriter,
    *,
    model_dir: str | os.PathLike,
    database: str = "posedb",
    device: str = "cpu",
    actors: int | tuple[int, int] = 2,
    batch_size: int = 8,
    threads: int = 1,
    options: BatchOptions | None = None,
    quiet: bool = False,
    address: str | None = None,
) -> None:
    """Estimates `paths` on a Ray Data actor pool, handing each result batch to `writer` as it
    comes. Joins the running Ray (ray.init already called), else the cluster at `address` (or
    $RAY_ADDRESS), else starts a local Ray for the run, shut down after. quiet: no progress
    bars nor Ray's info lines. Raises ImportError when Ray is not installed."""
    import ray

    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    level = os.environ.get("RAY_DATA_LOG_LEVEL")
    if quiet:  # Ray Data's own lines ("Starting execution", "execution finished") on stderr
        os.environ["RAY_DATA_LOG_LEVEL"] = "ERROR"
    started = not ray.is_initialized()
    if started:
        ray.init(
            address=address,
            include_dashboard=False,
            logging_level="ERROR" if quiet else "WARNING",
        )
    context = ray.data.DataContext.get_current()
    shown = context.enable_progress_bars, context.print_on_execution_start
    try:
        context.enable_progress_bars = not quiet
        context.print_on_execution_start = not quiet
        # a block per batch: small jobs still reach every actor
        blocks = max(1, min(math.ceil(len(paths) / batch_size), 10_000))
        dataset = ray.data.from_items([{"path": p} for p in paths], override_num_blocks=blocks)
        gpus = {"num_gpus": 1} if device == "cuda" else {}
        results = dataset.map_batches(
            Estimator,
            fn_constructor_kwargs={
                "model_dir": os.path.abspath(model_dir),  # the actors' folder may differ
                "database": database,
                "device": device,
                "options": asdict(options or BatchOptions()),
                "threads": threads,
            },
            batch_size=batch_size,
            batch_format="numpy",
            compute=ray.data.ActorPoolStrategy(
                min_size=actors if isinstance(actors, int) else actors[0],
                max_size=actors if isinstance(actors, int) else actors[1],
            ),
            num_cpus=threads,
            **gpus,
        )
        for batch in results.iter_batches(batch_size=None, batch_format="numpy"):
            writer.add(batch)
    finally:
        context.enable_progress_bars, context.print_on_execution_start = shown
        if started:
            ray.shutdown()
        if level is None:
            os.environ.pop("RAY_DATA_LOG_LEVEL", None)
        else:
            os.environ["RAY_DATA_LOG_LEVEL"] = level
