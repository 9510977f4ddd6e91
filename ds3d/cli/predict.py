"""`ds3d predict` (2D and 3D poses of images, folders, videos, a webcam or URLs, streamed in
batches: ds3d.runners.predict) and `ds3d gallery` (renders of LSP test images or of a folder of
photos)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from ds3d.cli.parser import (
    add_device_option,
    add_model_options,
    add_people_options,
    add_workers_option,
    load_pipeline,
)
from ds3d.fit.camera import ASSUMED_FOV_DEG


def register(commands, evals, benches) -> None:
    p = commands.add_parser(
        "predict",
        help="2D and 3D poses of the people in images, folders, videos, a webcam or URLs",
        description="Writes OUT/predictions.jsonl (a line per image or frame) and, for each "
        "video, OUT/NAME_3d.npz and .csv; the options add more (ds3d.io.writers).",
    )
    p.add_argument(
        "sources",
        nargs="+",
        help="image files, folders (every image below, found by content), globs, video files, "
        "a webcam index (0) or http(s) URLs",
    )
    p.add_argument("--out", type=Path, default=Path("predictions"), help="output folder")
    p.add_argument("--batch-size", type=int, default=16, help="images estimated at once")
    p.add_argument("--stride", type=int, default=1, help="every n-th frame of a video or webcam")
    add_people_options(p)
    p.add_argument(
        "--bbox",
        help="the person's box x,y,w,h in px, the same in every image (default: people are "
        "searched for; the Python API and the service take corners x0, y0, x1, y1)",
    )
    p.add_argument("--iterations", type=int, default=None, help="default: 1 (the paper's: 2)")
    p.add_argument(
        "--focal-px",
        type=float,
        help="the camera's focal length in px, which places the people in its coordinates "
        f"(root_position; default: a {ASSUMED_FOV_DEG:g}-degree field of view is assumed)",
    )
    p.add_argument(
        "--no-smooth",
        action="store_true",
        help="leave the 3D joints of videos and webcams as estimated frame by frame (by default "
        "each tracked person's are smoothed: ds3d.people.tracking)",
    )
    p.add_argument("--json", action="store_true", help="also OUT/json/: a JSON file per image")
    p.add_argument("--coco", action="store_true", help="also OUT/coco_keypoints.json")
    p.add_argument(
        "--bvh",
        action="store_true",
        help="also the joint angles as BVH: OUT/bvh/*.bvh per image and person (one frame), "
        "OUT/NAME_K.bvh per video and tracked person K",
    )
    p.add_argument(
        "--overlay",
        action="store_true",
        help="also the skeletons drawn: OUT/overlay/*.jpg per image, OUT/NAME_overlay.mp4 per "
        "video (2D over the frame, 3D beside it)",
    )
    add_device_option(p, "where both stages run")
    add_model_options(p, threads=None)  # --threads: with --workers, the machine's
    add_workers_option(p)
    p.set_defaults(func=predict)

    p = commands.add_parser("gallery", help="renders of LSP test images picked by a seed")
    p.add_argument("--n", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("docs/gallery"))
    p.add_argument(
        "--photos",
        type=Path,
        help="instead, every photo of this folder, every person found, into OUT/photos",
    )
    add_model_options(p)
    p.set_defaults(func=gallery)


def corner_box(text: str) -> tuple[float, float, float, float]:
    """'x,y,w,h' px -> (x0, y0, x1, y1), the 2D stage's box."""
    try:
        x, y, w, h = (float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"--bbox wants x,y,w,h in px; got {text!r}") from None
    return (x, y, x + w, y + h)


def predict(args) -> int:
    """Streams the sources through the pipeline in batches; a bad source is reported on stderr
    and in predictions.jsonl, and the run goes on."""
    from ds3d.io.writers import RunWriter
    from ds3d.runners.predict import predict as stream_predictions
    from ds3d.util.progress import progress

    pipeline = load_pipeline(args)
    skipped = []
    with (
        RunWriter(args.out, args.json, args.coco, args.overlay, args.stride, args.bvh) as out,
        progress(desc="predict", unit="img") as bar,
    ):

        def skip(frame) -> None:
            skipped.append(frame)
            out.skip(frame)
            bar.write(f"skipped {frame.source}: {frame.error}", file=sys.stderr)

        predictions = stream_predictions(
            args.sources,
            pipeline,
            batch_size=args.batch_size,
            stride=args.stride,
            bbox=None if args.bbox is None else corner_box(args.bbox),
            people=args.people,
            min_score=args.min_score,
            iterations=args.iterations,
            focal_px=args.focal_px,
            smooth=not args.no_smooth,
            on_skip=skip,
        )
        try:
            for prediction in predictions:
                out.write(prediction)
                bar.update()
        except KeyboardInterrupt:  # how a webcam run ends: what was estimated is kept
            print("interrupted", file=sys.stderr)
    print(f"{out.count} images, {len(skipped)} skipped: wrote {args.out}/", file=sys.stderr)
    return 0


def gallery(args) -> int:
    """Random picks, not the best ones: the gallery shows successes and failures alike."""
    from ds3d.data.lsp import load_lsp
    from ds3d.evaluation.metrics import pck
    from ds3d.io.images import read_image
    from ds3d.util.progress import progress
    from ds3d.viz.render import render

    pipeline = load_pipeline(args)
    if args.photos is not None:
        return gallery_of_photos(pipeline, args.photos, args.out / "photos")
    ann = load_lsp(split="test")
    picks = sorted(np.random.default_rng(args.seed).choice(len(ann), args.n, replace=False))
    with progress(total=len(picks), desc="gallery", unit="img") as bar:
        images = [read_image(ann.image_paths[i]) for i in picks]
        result = pipeline.estimate(images)  # one batch (the bar waits), then the renders
        args.out.mkdir(parents=True, exist_ok=True)
        gt = torch.from_numpy(ann.joints[picks])
        for j, i in enumerate(picks):
            name = ann.image_paths[i].stem
            correct = float(pck(result.joints_2d[j : j + 1], gt[j : j + 1]).mean())
            caption = (
                f"LSP {name}: joint set {result.joint_set[j]}, "
                f"{round(14 * correct)}/14 joints within PCK@0.2"
            )
            render(
                args.out / f"{name}.png",
                images[j],
                result.joints_2d[j].numpy(),
                result.joints_3d[j].numpy(),
                result.joints_2d_initial[j].numpy(),
                caption=caption,
            )
            bar.write(f"{args.out / f'{name}.png'} {caption}")
            bar.update()
    return 0


def gallery_of_photos(pipeline, folder: Path, out: Path) -> int:
    """Every JPEG or PNG photo of `folder` without a box, every person found, one render each."""
    from ds3d.io.images import read_image
    from ds3d.util.progress import progress
    from ds3d.viz.render import render

    out.mkdir(parents=True, exist_ok=True)
    photos = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    with progress(photos, desc="gallery", unit="img") as bar:
        for path in bar:
            image = read_image(path)
            found = pipeline.estimate([image], people="all")
            scores = ", ".join(f"{s:.2f}" for s in found.score.tolist())
            caption = f"{path.name}: {len(found.score)} people found (scores {scores or '-'})"
            render(
                out / f"{path.stem}.png",
                image,
                found.joints_2d.numpy(),
                found.joints_3d.numpy(),
                caption=caption,
                scores=found.score.numpy(),
            )
            bar.write(f"{out / f'{path.stem}.png'} {caption}")
    return 0
