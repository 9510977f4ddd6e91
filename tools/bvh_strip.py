"""The picture of the BVH path in the README: a Human3.6M sequence seen by one of its cameras as
a 2D track with 10 px of noise (the data holds no video), lifted frame by frame, followed as
`ds3d predict` follows a video's person (ds3d.people.tracking), written as BVH (ds3d.io.writers) and
read back with the project's BVH reader; its frames drawn over time, the 2D input above and the
file's skeleton by forward kinematics below, where it stands.

    python -m tools.bvh_strip docs/bvh-clip.png [--sequence "S11/Walking 1"] [--every 25]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from ds3d.data.bvh import forward_kinematics, read_bvh
from ds3d.data.h36m import load_cameras, load_h36m_sequences
from ds3d.io.writers import bvh_text
from ds3d.lifter import Lifter
from ds3d.people.tracking import follow
from ds3d.skeleton import LIMBS

FPS = 50.0  # Human3.6M's frame rate


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="PNG")
    parser.add_argument("--sequence", default="S11/Walking 1")
    parser.add_argument("--camera", type=int, default=1)
    parser.add_argument("--start", type=int, default=100, help="the first frame drawn")
    parser.add_argument("--every", type=int, default=15, help="frames between the drawn ones")
    parser.add_argument("--frames", type=int, default=8, help="frames drawn")
    parser.add_argument("--noise", type=float, default=10.0, help="px of noise on the 2D track")
    args = parser.parse_args(argv)
    subject = args.sequence.split("/")[0]
    poses = load_h36m_sequences((subject,))[args.sequence][: args.start + args.every * args.frames]
    camera = load_cameras()[(subject, args.camera)]
    rng = np.random.default_rng(0)
    track = camera.project(poses) + rng.normal(0.0, args.noise, (*poses.shape[:2], 2))
    lifted = Lifter.load().lift(track, intrinsics=np.repeat(camera.intrinsics[None], len(track), 0))
    assert lifted.root_position is not None  # placed by the intrinsics
    joints = follow((lifted.joints_3d + lifted.root_position[:, None]).numpy(), FPS)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "clip.bvh"
        path.write_text(bvh_text(joints, 1.0 / FPS))
        motion = read_bvh(path)
    drawn = args.start + np.arange(args.frames) * args.every
    positions = forward_kinematics(motion)  # (F, nodes, 3) mm, y up, x as the camera's
    figure, axes = plt.subplots(2, 1, figsize=(1.6 * args.frames, 5.6))
    for t, frame in enumerate(drawn):
        # each frame side by side: the 2D about its centre, the 3D about its root
        points = track[frame] - track[frame].mean(0) + np.array([t * 200.0, 0.0])
        for child, parent in LIMBS:
            axes[0].plot(*points[[child, parent]].T, color="tab:blue", lw=1.5)
        skeleton = positions[frame, :, :2] - positions[frame, 0, :2] * [1, 0] + [t * 1000.0, 0]
        for node, parent in enumerate(motion.parents):
            if parent >= 0:
                axes[1].plot(*skeleton[[node, parent]].T, color="tab:red", lw=1.5)
        away = -positions[frame, 0, 2] / 1000  # the world's z is the camera's, negated
        axes[1].text(t * 1000.0, positions[..., 1].min() - 150, f"{away:.1f} m away", ha="center")
    axes[0].set_title(
        f"the input: Human3.6M {args.sequence}, camera {args.camera}, as a 2D track with "
        f"{args.noise:g} px noise, every {args.every}th frame from frame {args.start}"
    )
    axes[0].invert_yaxis()
    axes[1].set_title(
        "its BVH file (followed, smoothed) read back with ds3d.data.bvh: forward kinematics, "
        "and how far the root stands from the camera"
    )
    for ax in axes:
        ax.set_aspect("equal")
        ax.axis("off")
    figure.tight_layout()
    figure.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
