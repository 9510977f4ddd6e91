#!/usr/bin/env bash
# ds3d against the tool people would use instead, MediaPipe Pose full (its person detector, its
# landmarks and its world 3D, mediapipe 0.10.14), on this machine's CPU, alternating in one run:
#
#   docker/peer_speed.sh [ROUNDS] [IMAGES]        (from a checkout after `make install`)
#
# Each round times MediaPipe (`static_image_mode=True, model_complexity=1`, one LSP test image at
# a time, the first IMAGES of im1001-im2000, default 64) and then `ds3d bench pipeline --threads
# $THREADS --workers $WORKERS --batch-sizes 16` (the first 16 LSP test images, people searched: no
# box; WORKERS=2 THREADS=1: two processes of one thread, ds3d.runners.workers), and prints both images/s
# and their ratio. MediaPipe runs in its own virtual environment ($PEER_VENV,
# default .peer-venv, made at the first run), so that none of its dependencies reach ds3d's.
set -euo pipefail
cd "$(dirname "$0")/.."

ROUNDS=${1:-2}
IMAGES=${2:-64}
THREADS=${THREADS:-2}
WORKERS=${WORKERS:-1}
DATA=${DS3D_DATA:-../shared/data}
PEER_VENV=${PEER_VENV:-.peer-venv}

if [ ! -x "$PEER_VENV/bin/python" ]; then
    python3 -m venv "$PEER_VENV"
    "$PEER_VENV/bin/pip" install --quiet mediapipe==0.10.14
fi
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

for round in $(seq "$ROUNDS"); do
    # MediaPipe's TensorFlow Lite logs to stderr: shown only when the run fails.
    OMP_NUM_THREADS=$THREADS "$PEER_VENV/bin/python" - "$DATA/lsp/images" "$IMAGES" \
        <<'PY' > "$out/peer" 2> "$out/peer.log" || { cat "$out/peer.log" >&2; exit 1; }
import sys
import time
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
print(f"{len(images) / seconds:.2f} {found}")
PY
    read -r peer found < "$out/peer"
    .venv/bin/ds3d bench pipeline --threads "$THREADS" --workers "$WORKERS" --batch-sizes 16 \
        --repeats 2 \
        --out "$out/ds3d.json" > /dev/null 2>&1
    ours=$(.venv/bin/python -c "import json, sys; print(json.load(open(sys.argv[1]))['rows'][0]['images_per_s'])" "$out/ds3d.json")
    ratio=$(.venv/bin/python -c "import sys; print(f'{float(sys.argv[1]) / float(sys.argv[2]):.2f}')" "$ours" "$peer")
    echo "round $round: MediaPipe Pose full $peer images/s (a pose in $found of $IMAGES images); ds3d searched, batch 16, $WORKERS x $THREADS threads: $ours images/s; ds3d / MediaPipe $ratio"
done
