"""Pictures of a result, after the paper's qualitative figure: the image with the 2D pose, and
the 3D pose from two viewpoints (the camera's, and from the person's side).

Matplotlib's object API on the Agg canvas: no display, no pyplot global state (safe in threads).
"""

from __future__ import annotations

from pathlib import Path

import mpl_toolkits.mplot3d  # noqa: F401  (registers the "3d" projection)
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ds3d.skeleton import LIMBS, NUM_JOINTS
from ds3d.viz import overlay


def limb_colour(child: int) -> tuple[float, float, float]:
    """ds3d.viz.overlay's colour of the limb ending at `child`, as matplotlib takes it."""
    red, green, blue = overlay.limb_colour(child)
    return red / 255, green / 255, blue / 255


def draw_2d(ax, image: np.ndarray, joints_2d: np.ndarray, initial: np.ndarray | None = None):
    """image: (H, W, 3) uint8; joints_2d: (14, 2) or (P, 14, 2) px, one skeleton per person;
    initial: optional (14, 2) px, drawn thin and grey under a single refined pose."""
    ax.imshow(image)
    if initial is not None:
        for child, parent in LIMBS:
            pts = initial[[child, parent]]
            ax.plot(pts[:, 0], pts[:, 1], color="0.85", lw=1, ls="--")
    for person in np.asarray(joints_2d).reshape(-1, NUM_JOINTS, 2):
        for child, parent in LIMBS:
            pts = person[[child, parent]]
            ax.plot(pts[:, 0], pts[:, 1], color=limb_colour(child), lw=2.5)
        ax.scatter(person[:, 0], person[:, 1], s=8, c="white", zorder=3)
    ax.set_xlim(-0.5, image.shape[1] - 0.5)
    ax.set_ylim(image.shape[0] - 0.5, -0.5)
    ax.axis("off")


def draw_3d(ax, joints_3d: np.ndarray, azimuth: float, title: str):
    """joints_3d: (14, 3) or (P, 14, 3) mm, camera-oriented (x right, y down, z away from the
    camera), each root-centred (several people stand side by side, a metre apart); drawn with
    the up axis up, seen from `azimuth` degrees around it (-90: the camera's view)."""
    people = np.asarray(joints_3d).reshape(-1, NUM_JOINTS, 3)
    people = people + np.arange(len(people))[:, None, None] * np.array([1000.0, 0.0, 0.0])
    everyone = people.reshape(-1, 3) if len(people) else np.zeros((1, 3))
    for person in people:
        x, depth, up = person[:, 0], person[:, 2], -person[:, 1]
        for child, parent in LIMBS:
            idx = [child, parent]
            ax.plot(x[idx], depth[idx], up[idx], color=limb_colour(child), lw=2.5)
    x, depth, up = everyone[:, 0], everyone[:, 2], -everyone[:, 1]
    centre = np.array([x.mean(), depth.mean(), up.mean()])
    radius = max(np.ptp(x), np.ptp(depth), np.ptp(up), 1.0) / 2
    for axis, c in zip("xyz", centre, strict=True):
        getattr(ax, f"set_{axis}lim")(c - radius, c + radius)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=10, azim=azimuth)
    ax.set_xticklabels([])
    ax.set_yticklabels([])
    ax.set_zticklabels([])
    ax.set_title(title, fontsize=9)


def render(
    path: str | Path,
    image: np.ndarray,
    joints_2d: np.ndarray,
    joints_3d: np.ndarray,
    initial_2d: np.ndarray | None = None,
    caption: str = "",
    scores: np.ndarray | None = None,
) -> None:
    """Write a PNG: the image with the 2D poses (px, (14, 2) or (P, 14, 2)) and the 3D poses
    (mm, (14, 3) or (P, 14, 3), camera-oriented) seen from the camera and from the side. With
    several people, scores (P,) labels each in the image, and the 3D views show them in the
    image's left-to-right order."""
    joints_2d = np.asarray(joints_2d).reshape(-1, NUM_JOINTS, 2)
    joints_3d = np.asarray(joints_3d).reshape(-1, NUM_JOINTS, 3)
    order = np.argsort(joints_2d[..., 0].mean(-1), kind="stable")
    aspect = image.shape[1] / image.shape[0]
    # the image's panel as wide as its aspect asks, beside two square 3D views
    fig = Figure(figsize=(3.2 * (max(aspect, 0.7) + 2), 3.6), dpi=100)
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(1, 3, width_ratios=[max(aspect, 0.7), 1, 1])
    ax = fig.add_subplot(grid[0])
    draw_2d(ax, image, joints_2d[order], initial_2d)
    if scores is not None:
        for person, score in zip(joints_2d, np.asarray(scores), strict=True):
            x, y = person[:, 0].min(), person[:, 1].min()
            ax.text(
                x,
                y,
                f"{score:.2f}",
                color="white",
                fontsize=8,
                va="bottom",
                bbox={"facecolor": "black", "alpha": 0.6, "pad": 1, "lw": 0},
            )
    draw_3d(fig.add_subplot(grid[1], projection="3d"), joints_3d[order], -90, "camera view")
    draw_3d(fig.add_subplot(grid[2], projection="3d"), joints_3d[order], 0, "side view")
    if caption:
        fig.suptitle(caption, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
