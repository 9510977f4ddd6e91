"""ds3d against the tool people would use instead, MediaPipe Pose full (its person detector, its
landmarks and its world 3D; mediapipe 0.10.14), on this machine's CPU, alternating in one run:

    python -m tools.peer_speed [--rounds 3] [--images 64] [--baseline WORKTREE] --out FILE.json

Each round times MediaPipe (`static_image_mode=True, model_complexity=1`, one LSP test image at a
time, the first IMAGES of im1001-im2000), then `ds3d bench pipeline --batch-sizes 16 --images
IMAGES --repeats 1` with the configuration a user gets by default (people searched, the best
person, worker processes and threads sized from the machine; `--ds3d-args` adds flags), then
`ds3d bench pipeline --batch-sizes 16 BASELINE_ARGS` in a `git worktree` of another commit where
one is given (--baseline; its own code, this checkout's environment), and reports images/s and
the ratios. MediaPipe runs in its
own virtual environment (--peer-venv, default .peer-venv, made at the first run), so that none
of its dependencies reach ds3d's. Nothing else should run meanwhile.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from ds3d.util.provenance import provenance

ROOT = Path(__file__).resolve().parents[1]
PEER = "mediapipe==0.10.14"
PEER_TIMING = """
import sys, time
from pathlib import Path
import cv2
import mediapipe as mp

folder, count = Path(sys.argv[1]), int(sys.argv[2])
paths = [folder / f"im{i:04d}.jpg" for i in range(1001, 1001 + count)]
images = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in paths]
with mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1) as pose:
    pose.process(images[0])  # warm-up
    start = time.perf_counter()
    found = sum(pose.process(image).pose_world_landmarks is not None for image in images)
    seconds = time.perf_counter() - start
print(len(images) / seconds, found)
"""


def peer_venv(path: Path) -> Path:
    """The peer's python, its virtual environment made where missing."""
    python = path / "bin" / "python"
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(path)], check=True)
        subprocess.run([str(path / "bin" / "pip"), "install", "--quiet", PEER], check=True)
    return python


def peer_images_per_s(python: Path, images: Path, count: int) -> tuple[float, int]:
    """MediaPipe's images/s over the first `count` LSP test images, and on how many it found a
    pose. Its TensorFlow Lite log goes to stderr, shown only when the run fails."""
    run = subprocess.run(
        [str(python), "-c", PEER_TIMING, str(images), str(count)], capture_output=True, text=True
    )
    if run.returncode != 0:
        raise SystemExit(f"MediaPipe failed:\n{run.stderr[-2000:]}")
    rate, found = run.stdout.split()
    return float(rate), int(found)


def ds3d_images_per_s(tree: Path, flags: list[str]) -> dict:
    """`ds3d bench pipeline --batch-sizes 16 FLAGS` of the checkout `tree` (this environment's
    interpreter, the tree's own code): its one row (images/s, ms per stage) and settings."""
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "bench.json"
        command = [sys.executable, "-m", "ds3d.cli", "--quiet", "bench", "pipeline"]
        command += ["--batch-sizes", "16", *flags, "--out", str(out)]
        env = {**os.environ, "PYTHONPATH": str(tree)}
        subprocess.run(command, cwd=tree, env=env, check=True, capture_output=True)
        report = json.loads(out.read_text())
    row = report["rows"][0]
    return {
        "images_per_s": row["images_per_s"],
        "workers": report["workers"],
        "threads": report["threads"],
        "ms_per_image": row["ms_per_image"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--images", type=int, default=64, help="different LSP test images")
    parser.add_argument("--baseline", type=Path, help="a git worktree of another commit")
    parser.add_argument("--ds3d-args", default="", help="more `ds3d bench pipeline` flags")
    parser.add_argument(
        "--baseline-args",
        default="--repeats 4",
        help="the baseline's `ds3d bench pipeline` flags beside --batch-sizes 16 (a tree whose "
        "bench has no --images times its first 16 images, --repeats times)",
    )
    parser.add_argument("--peer-venv", type=Path, default=ROOT / ".peer-venv")
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(os.environ.get("DS3D_DATA", ROOT.parent / "shared" / "data")),
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    python = peer_venv(args.peer_venv)
    images = args.data / "lsp" / "images"
    flags = ["--images", str(args.images), "--repeats", "1", *args.ds3d_args.split()]
    rounds = []
    for k in range(args.rounds):
        rate, found = peer_images_per_s(python, images, args.images)
        ours = ds3d_images_per_s(ROOT, flags)
        row: dict = {"mediapipe": {"images_per_s": round(rate, 2), "poses_found": found}}
        row["ds3d"] = ours
        row["ds3d_over_mediapipe"] = round(ours["images_per_s"] / rate, 3)
        if args.baseline is not None:
            theirs = ds3d_images_per_s(args.baseline, args.baseline_args.split())
            row["baseline"] = theirs
            row["ds3d_over_baseline"] = round(ours["images_per_s"] / theirs["images_per_s"], 3)
        print(f"round {k + 1}: {json.dumps(row)}", file=sys.stderr)
        rounds.append(row)
    summary = {
        key: statistics.median(r[key] for r in rounds)
        for key in ("ds3d_over_mediapipe", "ds3d_over_baseline")
        if key in rounds[0]
    }
    summary |= {
        f"{who}_images_per_s": statistics.median(r[who]["images_per_s"] for r in rounds)
        for who in ("mediapipe", "ds3d", "baseline")
        if who in rounds[0]
    }
    report = {
        "images": f"LSP test im1001-im{1000 + args.images:04d}, people searched, best person",
        "baseline": None if args.baseline is None else _commit(args.baseline),
        "ds3d_args": args.ds3d_args,
        "baseline_args": None if args.baseline is None else args.baseline_args,
        "median": summary,
        "rounds": rounds,
        "provenance": provenance(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(summary))
    return 0


def _commit(tree: Path) -> str:
    run = subprocess.run(
        ["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    return run.stdout.strip()


if __name__ == "__main__":
    sys.exit(main())
