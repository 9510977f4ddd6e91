"""Readers for Leeds Sports Pose (LSP) and LSP-extended (LSPet).

Both give 14 joints in LSP order (ds3d.skeleton). The readers convert at the edge:
- MATLAB 1-based pixel coordinates become 0-based (x - 1, y - 1), so pixel (0, 0) is the centre
  of the top-left pixel, as in OpenCV and torch.
- Visibility becomes one convention, True = visible: LSP stores 0 = visible (inverted), LSPet
  stores 1 = visible.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io

from ds3d.errors import DataFormatError
from ds3d.util.paths import data_root

LSP_TRAIN = range(0, 1000)  # im0001-im1000, 0-based indices
LSP_TEST = range(1000, 2000)  # im1001-im2000


@dataclass(frozen=True)
class PoseAnnotations:
    """2D annotations of a set of images.

    image_paths: N paths; joints: (N, 14, 2) float32, 0-based pixels;
    visible: (N, 14) bool, True where the joint is annotated as visible;
    located: (N, 14) bool, True where its position is annotated, visible or not (LSP places
    occluded joints, LSPet does not).
    """

    image_paths: tuple[Path, ...]
    joints: np.ndarray
    visible: np.ndarray
    located: np.ndarray

    def __len__(self) -> int:
        return len(self.image_paths)

    def subset(self, indices) -> PoseAnnotations:
        idx = np.asarray(list(indices), dtype=np.int64)
        return PoseAnnotations(
            tuple(self.image_paths[i] for i in idx),
            self.joints[idx],
            self.visible[idx],
            self.located[idx],
        )

    def concat(self, other: PoseAnnotations) -> PoseAnnotations:
        return PoseAnnotations(
            self.image_paths + other.image_paths,
            np.concatenate([self.joints, other.joints]),
            np.concatenate([self.visible, other.visible]),
            np.concatenate([self.located, other.located]),
        )


def _load_joints(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataFormatError(f"missing annotation file {path}")
    try:
        joints = scipy.io.loadmat(str(path))["joints"]
    except (KeyError, ValueError, OSError) as exc:
        raise DataFormatError(f"cannot read 'joints' from {path}: {exc}") from exc
    return np.asarray(joints, dtype=np.float64)


def load_lsp(root: Path | None = None, split: str = "all") -> PoseAnnotations:
    """LSP: `joints.mat` holds (3, 14, 2000) = (x, y, flag), flag 0 = visible.

    split: "train" (im0001-im1000), "test" (im1001-im2000) or "all".
    """
    root = Path(root) if root is not None else data_root() / "lsp"
    raw = _load_joints(root / "joints.mat")
    if raw.shape != (3, 14, 2000):
        raise DataFormatError(f"LSP joints.mat has shape {raw.shape}, expected (3, 14, 2000)")
    arr = raw.transpose(2, 1, 0)  # (2000, 14, 3)
    ann = PoseAnnotations(
        tuple(root / "images" / f"im{i + 1:04d}.jpg" for i in range(2000)),
        (arr[..., :2] - 1.0).astype(np.float32),
        arr[..., 2] == 0,
        np.ones(arr.shape[:2], dtype=bool),
    )
    ranges = {"train": LSP_TRAIN, "test": LSP_TEST, "all": range(2000)}
    if split not in ranges:
        raise ValueError(f"split must be one of {sorted(ranges)}, got {split!r}")
    return ann.subset(ranges[split])


def load_lspet(root: Path | None = None) -> PoseAnnotations:
    """LSPet: `joints.mat` holds (14, 3, 10000) = (x, y, flag), flag 1 = visible.

    Invisible joints may hold junk coordinates: use `visible` as a mask.
    """
    root = Path(root) if root is not None else data_root() / "lspet"
    raw = _load_joints(root / "joints.mat")
    if raw.ndim != 3 or raw.shape[:2] != (14, 3):
        raise DataFormatError(f"LSPet joints.mat has shape {raw.shape}, expected (14, 3, N)")
    arr = raw.transpose(2, 0, 1)  # (N, 14, 3)
    n = arr.shape[0]
    return PoseAnnotations(
        tuple(root / "images" / f"im{i + 1:05d}.jpg" for i in range(n)),
        (arr[..., :2] - 1.0).astype(np.float32),
        arr[..., 2] == 1,
        arr[..., 2] == 1,
    )
