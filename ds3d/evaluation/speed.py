"""Speed and memory, measured: the 3D stage's poses/s (lift_speed), retrieval's recall against
exact search (retrieval_recall), the 2D stage's and the pipeline's images/s (estimator_speed,
pipeline_speed), resident memory over a stream of images (memory_stream). Each returns a report
of what it measured; none gates. Inputs: LSP test images where the dataset is present, or
plausible stand-ins without it (bench_images, benchmark_poses)."""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Callable

import cv2
import numpy as np
import torch

from ds3d.lifter import Lifter
from ds3d.skeleton import SET_NAMES
from ds3d.util.memory import glibc_heap_mb, loaded_allocator, malloc_trim, resident_mb
from ds3d.util.progress import progress

# The environment that changes how memory is allocated, recorded in memory_stream's report.
MEMORY_ENV_PREFIXES = ("MALLOC_", "LD_PRELOAD", "ONEDNN_", "DNNL_")


def bench_images(n: int, size: tuple[int, int] | None = None) -> list[np.ndarray]:
    """n LSP test images (resized to size = (w, h) if given), or noise of LSP's typical size
    where the dataset is absent."""
    from ds3d.data.lsp import load_lsp
    from ds3d.io.images import read_image
    from ds3d.util.paths import data_root

    if (data_root() / "lsp" / "joints.mat").is_file():
        images = [read_image(p) for p in load_lsp(split="test").image_paths[:n]]
    else:
        rng = np.random.default_rng(0)
        images = [rng.integers(0, 256, (175, 110, 3), dtype=np.uint8) for _ in range(n)]
    if size is not None:
        images = [cv2.resize(im, size, interpolation=cv2.INTER_LINEAR) for im in images]
    return images


def bench_boxes(n: int) -> list[np.ndarray]:
    """The person boxes (x0, y0, x1, y1) px of bench_images(n), from the LSP annotations."""
    from ds3d.boxes import person_boxes
    from ds3d.data.lsp import load_lsp

    return list(person_boxes(load_lsp(split="test").joints[:n]).astype(np.float32))


def benchmark_poses(lifter: Lifter, count: int, seed: int = 0) -> np.ndarray:
    """Plausible 2D inputs without any dataset: database poses seen from random virtual views,
    scaled to ~400 px tall in a 1000 x 1000 image. Returns (count, 14, 2) float32 px."""
    rng = np.random.default_rng(seed)
    db = lifter.database
    ids = torch.from_numpy(rng.integers(0, len(db), count))
    poses = db.candidates(ids.to(db.poses.device)).cpu().numpy()
    return (poses[..., :2] * 0.22 + 500).astype(np.float32)


def lift_speed(lifter: Lifter, batch_sizes: list[int], repeats: int) -> dict:
    """Lifter.lift's poses/s and ms per stage at each batch size, after a warm-up batch, over
    `repeats` batches of other poses; the process's peak resident memory."""
    report: dict = {"device": str(lifter.device), "threads": torch.get_num_threads()}
    report["batches"] = {}
    for batch in batch_sizes:
        inputs = benchmark_poses(lifter, batch * (repeats + 1))
        lifter.lift(inputs[:batch])  # warm-up
        stages: dict[str, float] = {}
        elapsed = 0.0
        with progress(total=batch * repeats, desc=f"batch {batch}", unit="pose") as bar:
            for r in range(1, repeats + 1):
                t = time.perf_counter()
                result = lifter.lift(inputs[r * batch : (r + 1) * batch])
                elapsed += time.perf_counter() - t
                for stage, ms in result.timings_ms.items():
                    stages[stage] = stages.get(stage, 0.0) + ms / repeats
                bar.update(batch)
        report["batches"][batch] = {
            "poses_per_s": round(batch * repeats / elapsed, 1),
            "ms_per_batch": {k: round(v, 1) for k, v in stages.items()},
        }
    report["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return report


def retrieval_recall(lifter: Lifter, queries: int, k: int, nprobes: list[int]) -> dict:
    """Recall@k of the lifter's IVF index against an exact flat index, per set, and the time
    per query of each, on plausible queries (benchmark_poses plus 5 px of noise)."""
    from ds3d.mocap.retrieval import IndexConfig, PoseRetriever

    rng = np.random.default_rng(1)
    noisy = benchmark_poses(lifter, queries) + rng.normal(0, 5, (queries, 14, 2))
    query = torch.from_numpy(noisy.astype(np.float32))
    exact = PoseRetriever(lifter.database, IndexConfig(kind="flat", storage="f32"), cache=False)
    with progress(total=queries * (1 + len(nprobes)), desc="retrieval", unit="query") as bar:
        start = time.perf_counter()
        truth = exact.search(query, k)
        report: dict = {
            "k": k,
            "queries": queries,
            "flat_ms_per_query": round(1000 * (time.perf_counter() - start) / queries, 2),
            "ivf": {},
        }
        del exact
        bar.update(queries)
        for nprobe in nprobes:
            start = time.perf_counter()
            found = lifter.retriever.search(query, k, nprobe)
            elapsed = time.perf_counter() - start
            bar.update(queries)
            recall = {
                name: float(
                    np.mean(
                        [
                            len(set(f.tolist()) & set(t.tolist())) / k
                            for f, t in zip(found[:, s], truth[:, s], strict=True)
                        ]
                    )
                )
                for s, name in enumerate(SET_NAMES)
            }
            report["ivf"][nprobe] = {
                "ms_per_query": round(1000 * elapsed / queries, 2),
                "recall": {name: round(v, 3) for name, v in recall.items()},
            }
    return report


def estimator_speed(estimator, repeats: int) -> list[dict]:
    """PoseEstimator2D.estimate's images/s and ms per step (summed over its threads; total is
    wall-clock) on LSP-sized and 640 x 480 images, at batch 1 and 16, after a warm-up."""
    rows = []
    for label, size in (("lsp-sized", None), ("640x480", (640, 480))):
        images = bench_images(16, size)
        for batch in (1, 16):
            estimator.estimate(images[:batch])  # warm-up
            steps = dict.fromkeys(("features", "traversal", "jointnet", "psm", "total"), 0.0)
            with progress(total=repeats * batch, desc=f"{label} x{batch}", unit="img") as bar:
                for _ in range(repeats):
                    res = estimator.estimate(images[:batch])
                    for k in steps:
                        steps[k] += res.timings[k]
                    bar.update(batch)
            n = repeats * batch
            rows.append(
                {
                    "image": label,
                    "shape": list(images[0].shape[:2]),
                    "batch": batch,
                    "images_per_s": round(n / steps["total"], 2),
                    "ms_per_image": {k: round(1000 * v / n, 1) for k, v in steps.items()},
                }
            )
    return rows


def pipeline_speed(pipeline, batch: int, images: int, repeats: int, boxes: bool = False) -> dict:
    """The pipeline's images/s and ms per stage at one batch size, wall-clock, over `repeats`
    passes through `images` different LSP test images (bench_images) in batches of `batch`
    (their people searched, the best person of each; boxes: each with its person's box), after
    a warm-up batch. Stage times are summed over its threads or worker processes."""
    pool = bench_images(images)
    given = bench_boxes(len(pool)) if boxes else None
    parts = [range(i, min(i + batch, len(pool))) for i in range(0, len(pool), batch)]

    def run(rows: range) -> dict[str, float]:
        bboxes = None if given is None else [given[i] for i in rows]
        return pipeline.estimate([pool[i] for i in rows], bboxes).timings_ms

    run(parts[0])  # warm-up
    stages: dict[str, float] = {}
    with progress(total=repeats * len(pool), desc=f"batch {batch}", unit="img") as bar:
        start = time.perf_counter()
        for _ in range(repeats):
            for rows in parts:
                for stage, ms in run(rows).items():
                    stages[stage] = stages.get(stage, 0.0) + ms
                bar.update(len(rows))
        seconds = time.perf_counter() - start
    n = repeats * len(pool)
    return {
        "batch": batch,
        "images": len(pool),
        "images_per_s": round(n / seconds, 2),
        "ms_per_image": {k: round(v / n, 1) for k, v in stages.items()},
    }


def memory_stream(
    estimate: Callable[[np.ndarray], object], images: int, every: int, trim: bool
) -> dict:
    """estimate(image) on `images` LSP test images one at a time, as a service sees them (each a
    new size): the resident memory every `every` images and its growth from the first report
    (after warm-up) to the end; trim: glibc's malloc_trim after each image. Run it under each
    allocator (LD_PRELOAD, MALLOC_* env vars)."""
    from ds3d.data.lsp import load_lsp
    from ds3d.io.images import read_image

    paths = load_lsp(split="test").image_paths[:images]
    rows = []
    start = time.perf_counter()
    for i, path in enumerate(progress(paths, desc="images", unit="img"), start=1):
        estimate(read_image(path))
        if trim:
            malloc_trim()
        if i % every == 0 or i == len(paths):
            rows.append({"images": i, "rss_mb": round(resident_mb(), 1)} | (glibc_heap_mb() or {}))
    seconds = time.perf_counter() - start
    first, last = rows[0]["rss_mb"], rows[-1]["rss_mb"]
    return {
        "allocator": loaded_allocator(),
        "malloc_trim": trim,
        "env": {k: v for k, v in os.environ.items() if k.startswith(MEMORY_ENV_PREFIXES)},
        "rss_mb": rows,
        "growth_pct": round(100 * (last - first) / first, 1),
        "s_per_image": round(seconds / len(paths), 3),
    }
