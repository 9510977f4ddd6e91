"""The 3D pose database: deduplicated body-frame poses from a mocap source, and what the
paper derives from them (each pose seen by the 144 virtual cameras, normalised in 2D).

On disk a database is a directory with `poses.npy` ((N, 14, 3) float32, mm, body frame) and
`manifest.json` (source, subjects or files, dedupe threshold, counts, seed-free: it is
deterministic). The projected 2D vectors are never stored: they are recomputed from the poses
(see ds3d.mocap.retrieval), which keeps the model small.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import faiss
import numpy as np
import torch

from ds3d.errors import DataFormatError
from ds3d.mocap.normalize import normalize_2d, normalize_3d
from ds3d.mocap.views import rotate, view_rotations
from ds3d.skeleton import JOINT_SETS, NUM_JOINTS
from ds3d.util.progress import progress


def deduplicate(poses: np.ndarray, threshold_mm: float, chunk: int = 4096) -> np.ndarray:
    """Greedy near-duplicate removal in the given order.

    A pose is dropped when an already kept pose lies within `threshold_mm` root-mean-square
    joint distance (RMS >= the paper's mean joint distance, so this drops no pose the paper's
    criterion would keep). poses: (N, 14, 3) float32, mm. Returns the kept indices (M,) int64.
    """
    flat = np.ascontiguousarray(poses.reshape(len(poses), -1), dtype=np.float32)
    limit = threshold_mm**2 * NUM_JOINTS  # squared L2 in R^42
    kept_index = faiss.IndexFlatL2(flat.shape[1])
    kept: list[np.ndarray] = []
    with progress(total=len(flat), desc="dedupe", unit="pose") as bar:
        for start in range(0, len(flat), chunk):
            block = flat[start : start + chunk]
            if kept_index.ntotal:
                nearest, _ = kept_index.search(block, 1)
                fresh = np.flatnonzero(nearest[:, 0] >= limit)
            else:
                fresh = np.arange(len(block))
            # Greedy within the block: consecutive mocap frames are the closest pairs.
            block_t = torch.from_numpy(block[fresh])
            dist = torch.cdist(block_t, block_t).square_() < limit
            taken = torch.zeros(len(fresh), dtype=torch.bool)
            alive = torch.ones(len(fresh), dtype=torch.bool)
            for i in range(len(fresh)):
                if alive[i]:
                    taken[i] = True
                    alive &= ~dist[i]
            chosen = fresh[taken.numpy()]
            kept_index.add(block[chosen])
            kept.append(start + chosen)
            bar.update(len(block))
    return np.concatenate(kept).astype(np.int64)


@dataclass
class PoseDatabase:
    """Body-frame 3D poses and the virtual cameras that view them.

    poses: (N, 14, 3) float32, mm, body frame (ds3d.mocap.normalize). rotations: (V, 3, 3) the
    virtual views (ds3d.mocap.views). Entry id = pose * V + view.
    """

    poses: torch.Tensor
    rotations: torch.Tensor = field(default_factory=view_rotations)
    manifest: dict = field(default_factory=dict)

    @classmethod
    def from_world_poses(
        cls, poses: np.ndarray, dedupe_mm: float, manifest: dict | None = None
    ) -> PoseDatabase:
        """Normalise world poses (N, 14, 3) mm (z up), drop near-duplicates, build."""
        body = normalize_3d(torch.from_numpy(np.asarray(poses, dtype=np.float32))).numpy()
        kept = deduplicate(body, dedupe_mm)
        info = dict(manifest or {}, dedupe_mm=dedupe_mm, poses_in=len(poses), poses=len(kept))
        return cls(torch.from_numpy(body[kept]), manifest=info)

    @property
    def num_views(self) -> int:
        return len(self.rotations)

    def __len__(self) -> int:
        return len(self.poses) * self.num_views

    def candidates(self, ids: torch.Tensor) -> torch.Tensor:
        """Entries as 3D poses in the orientation of the camera that saw them.

        ids: (...) int64 entry ids. Returns (..., 14, 3) float32 mm: x right, y down, z away
        from the virtual camera, root at the hip midpoint.
        """
        ids = ids.clamp_min(0)  # faiss pads missing neighbours with -1
        return rotate(self.poses[ids // self.num_views], self.rotations[ids % self.num_views])

    def projected_2d(self, joint_set: str, chunk: int = 8192) -> Iterator[np.ndarray]:
        """The normalised 2D vectors of every entry for one joint set, in id order, in chunks
        of `chunk` poses: each (chunk * V, 2 * |set|) float32, C-contiguous for faiss."""
        joints = list(JOINT_SETS[joint_set])
        for start in range(0, len(self.poses), chunk):
            views = rotate(self.poses[start : start + chunk, None, joints], self.rotations[None])
            flat = normalize_2d(views[..., :2]).reshape(-1, 2 * len(joints))
            yield np.ascontiguousarray(flat.numpy(), dtype=np.float32)

    def save(self, directory: Path) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        np.save(directory / "poses.npy", self.poses.numpy().astype(np.float32))
        manifest = dict(self.manifest, num_views=self.num_views)
        (directory / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")

    @classmethod
    def load(cls, directory: Path) -> PoseDatabase:
        try:
            poses = np.load(directory / "poses.npy")
            manifest = json.loads((directory / "manifest.json").read_text())
        except (OSError, ValueError) as err:
            raise DataFormatError(f"{directory}: not a pose database ({err})") from err
        if poses.ndim != 3 or poses.shape[1:] != (NUM_JOINTS, 3):
            raise DataFormatError(f"{directory}/poses.npy: expected (N, 14, 3), got {poses.shape}")
        return cls(torch.from_numpy(poses.astype(np.float32)), manifest=manifest)
