"""Human3.6M readers: 3D joint positions (npz) and cameras (cameras.h5, 3d-pose-baseline layout).

World coordinates are millimetres with z up. Poses are converted to the 14 LSP-order joints here,
at the edge, with ds3d.skeleton.H36M17_TO_LSP.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ds3d.errors import DataFormatError
from ds3d.skeleton import H36M17_TO_LSP
from ds3d.util.paths import data_root

TRAIN_SUBJECTS: tuple[str, ...] = ("S1", "S5", "S6", "S7", "S8", "S9")
TEST_SUBJECT = "S11"


def poses_path(root: Path | None = None) -> Path:
    return (root or data_root()) / "h36m" / "poses_3d_17j.npz"


def cameras_path(root: Path | None = None) -> Path:
    return (root or data_root()) / "h36m" / "cameras.h5"


def action_name(sequence: str) -> str:
    """'Walking 1' -> 'Walking'; 'WalkDog' stays 'WalkDog'."""
    return sequence.split(" ")[0]


def load_h36m_sequences(
    subjects: tuple[str, ...] = TRAIN_SUBJECTS, path: Path | None = None
) -> dict[str, np.ndarray]:
    """The sequences of `subjects` as {"S9/Walking 1": (N, 14, 3) float32 mm, world, z up}."""
    path = path or poses_path()
    if not path.is_file():
        raise DataFormatError(f"Human3.6M poses not found at {path} (set $DS3D_DATA)")
    try:
        archive = np.load(path)
    except (OSError, ValueError) as err:
        raise DataFormatError(f"{path}: not a readable npz archive ({err})") from err
    with archive:
        wanted = sorted(k for k in archive.files if k.split("/")[0] in subjects)
        if not wanted:
            raise DataFormatError(f"{path}: no sequence of subjects {subjects}")
        sequences = {}
        for key in wanted:
            poses = archive[key]
            if poses.ndim != 3 or poses.shape[1:] != (17, 3):
                raise DataFormatError(f"{path}[{key}]: expected (N, 17, 3), got {poses.shape}")
            sequences[key] = poses[:, H36M17_TO_LSP].astype(np.float32)
    return sequences


def load_h36m_poses(subjects: tuple[str, ...] = TRAIN_SUBJECTS, path: Path | None = None):
    """All poses of `subjects` stacked: (N, 14, 3) float32 mm, world, z up."""
    return np.concatenate(list(load_h36m_sequences(subjects, path).values()))


@dataclass(frozen=True)
class Camera:
    """A Human3.6M camera. X_cam = R @ (X - T); uv = f * X_cam[:2] / X_cam[2] + c."""

    R: np.ndarray  # (3, 3) world -> camera rotation
    T: np.ndarray  # (3,) camera centre in world, mm
    f: np.ndarray  # (2,) focal lengths, px
    c: np.ndarray  # (2,) principal point, px

    @property
    def intrinsics(self) -> np.ndarray:
        """(3, 3) float32 pinhole matrix K."""
        return np.array(
            [[self.f[0], 0, self.c[0]], [0, self.f[1], self.c[1]], [0, 0, 1]], dtype=np.float32
        )

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) mm -> camera frame (..., 3) mm (x right, y down, z forward)."""
        return ((points - self.T) @ self.R.T).astype(np.float32)

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) mm -> pixels (..., 2), distortion ignored."""
        cam = self.to_camera(points)
        return (self.f * cam[..., :2] / cam[..., 2:3] + self.c).astype(np.float32)


def load_cameras(path: Path | None = None) -> dict[tuple[str, int], Camera]:
    """{("S11", 1): Camera, ...} for every subject and camera 1-4 in cameras.h5."""
    import h5py

    path = path or cameras_path()
    if not path.is_file():
        raise DataFormatError(f"Human3.6M cameras not found at {path} (set $DS3D_DATA)")
    cameras = {}
    try:
        with h5py.File(path, "r") as h5:
            for group in h5:
                if not group.startswith("subject"):
                    continue
                subject = "S" + group.removeprefix("subject")
                for cam_name, cam in h5[group].items():
                    cameras[(subject, int(cam_name.removeprefix("camera")))] = Camera(
                        R=cam["R"][:].T.astype(np.float64),  # stored transposed
                        T=cam["T"][:].reshape(3),
                        f=cam["f"][:].reshape(2),
                        c=cam["c"][:].reshape(2),
                    )
    except (OSError, KeyError) as err:
        raise DataFormatError(f"{path}: not a cameras.h5 in the expected layout ({err})") from err
    return cameras
