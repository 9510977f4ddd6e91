"""The paper's Human3.6M protocol (Section 5.2, with ground-truth 2D).

Database from S1, S5, S6, S7, S8, S9; test on every 64th frame of every S11 sequence, seen by all
four cameras; the 2D input is the ground truth projected with the real camera and the lifter gets
the intrinsics. Error: the paper's 3D pose error (rigid alignment, no scale), with PA-MPJPE and
MPJPE (root-aligned at the hip midpoint) beside it, per action and averaged over all frames.

Robustness variants perturb the 2D input: Gaussian noise of sigma px on every coordinate, or one
random joint per pose displaced by a fixed distance in a random direction.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch

from ds3d.data.h36m import TEST_SUBJECT, action_name, load_cameras, load_h36m_sequences
from ds3d.evaluation.metrics import mpjpe, pa_mpjpe, rigid_error
from ds3d.fit.bones import scaling_map
from ds3d.lifter import PAPER_OVERRIDES, UNWEIGHTED_OVERRIDES
from ds3d.people.tracking import follow, jitter
from ds3d.skeleton import BONE_GROUPS, NUM_JOINTS, hip_midpoint
from ds3d.util.progress import progress


@dataclass
class ProtocolCases:
    """N test poses. joints_2d (N, 14, 2) px; joints_3d (N, 14, 3) mm in the camera frame, root
    at the hip midpoint; roots (N, 3) mm, the hip midpoint in the camera frame; intrinsics
    (N, 3, 3); action (N,) names; camera (N,) 1-4."""

    joints_2d: np.ndarray
    joints_3d: np.ndarray
    roots: np.ndarray
    intrinsics: np.ndarray
    action: np.ndarray
    camera: np.ndarray

    def __len__(self) -> int:
        return len(self.joints_2d)

    def subset(self, index) -> ProtocolCases:
        return ProtocolCases(*(getattr(self, f)[index] for f in self.__dataclass_fields__))


def protocol_cases(
    subject: str = TEST_SUBJECT, stride: int = 64, proportions: dict[str, float] | None = None
) -> ProtocolCases:
    """Every `stride`-th frame of every sequence of `subject`, four cameras each. proportions:
    optional {bone group (ds3d.skeleton.BONE_GROUPS): scale}: the subject's bones so scaled
    (the rest as they are) before the poses are seen by the cameras, a person of other
    proportions in the same motion."""
    sequences = load_h36m_sequences((subject,))
    cameras = load_cameras()
    scaling = None if not proportions else scaling_map(group_scales(proportions)).numpy()
    parts: dict[str, list] = {f: [] for f in ProtocolCases.__dataclass_fields__}
    for key, poses in sequences.items():
        frames = poses[::stride] if scaling is None else scaling @ poses[::stride]
        for cam_id in (1, 2, 3, 4):
            camera = cameras[(subject, cam_id)]
            in_camera = camera.to_camera(frames)
            parts["joints_2d"].append(camera.project(frames))
            roots = hip_midpoint(in_camera)
            parts["joints_3d"].append(in_camera - roots[:, None])
            parts["roots"].append(roots)
            parts["intrinsics"].append(np.repeat(camera.intrinsics[None], len(frames), 0))
            parts["action"].append(np.full(len(frames), action_name(key.split("/")[1])))
            parts["camera"].append(np.full(len(frames), cam_id))
    return ProtocolCases(*(np.concatenate(parts[f]) for f in ProtocolCases.__dataclass_fields__))


def group_scales(proportions: dict[str, float]) -> torch.Tensor:
    """{bone group: scale} -> (G,) scales in BONE_GROUPS order, 1 for the groups not named.
    Raises ValueError on an unknown group."""
    unknown = set(proportions) - set(BONE_GROUPS)
    if unknown:
        raise ValueError(f"unknown bone groups {sorted(unknown)}; known: {', '.join(BONE_GROUPS)}")
    return torch.tensor([float(proportions.get(g, 1.0)) for g in BONE_GROUPS])


def perturb(
    joints_2d: np.ndarray, noise_px: float = 0.0, outlier_px: float = 0.0, seed: int = 0
) -> np.ndarray:
    """Gaussian noise of `noise_px` on every coordinate and/or one random joint per pose moved
    by `outlier_px` in a random direction. joints_2d: (N, 14, 2) px."""
    rng = np.random.default_rng(seed)
    out = joints_2d + rng.normal(0.0, noise_px, joints_2d.shape) if noise_px else joints_2d.copy()
    if outlier_px:
        joint = rng.integers(0, NUM_JOINTS, len(out))
        angle = rng.uniform(0, 2 * np.pi, len(out))
        out[np.arange(len(out)), joint] += outlier_px * np.stack([np.cos(angle), np.sin(angle)], 1)
    return out.astype(np.float32)


def lift_all(
    lifter, cases: ProtocolCases, joints_2d: np.ndarray, batch_size: int = 64, desc: str = "lift"
):
    """Lift every case in batches (a progress bar named `desc`), with its camera's intrinsics.
    Returns the 3D poses (N, 14, 3), their roots in camera coordinates (N, 3) and the chosen
    sets (N,)."""
    poses, roots, sets = [], [], []
    with progress(total=len(cases), desc=desc, unit="pose") as bar:
        for start in range(0, len(cases), batch_size):
            part = slice(start, start + batch_size)
            result = lifter.lift(joints_2d[part], intrinsics=cases.intrinsics[part])
            assert result.root_position is not None  # placed by the intrinsics
            poses.append(result.joints_3d.numpy())
            roots.append(result.root_position.numpy())
            sets.extend(result.joint_set)
            bar.update(len(poses[-1]))
    return np.concatenate(poses), np.concatenate(roots), np.array(sets)


def score(
    pred: np.ndarray,
    cases: ProtocolCases,
    sets: np.ndarray | None = None,
    roots: np.ndarray | None = None,
) -> dict:
    """Errors (mm) per action and overall (mean over frames) + how often each set was chosen.
    With the predicted roots (N, 3) mm in camera coordinates also the people's placement: the
    mean root position error (mrpe) and the camera-space MPJPE without any alignment."""
    errors = {
        "pose_error": rigid_error(pred, cases.joints_3d).numpy(),
        "pa_mpjpe": pa_mpjpe(pred, cases.joints_3d).numpy(),
        "mpjpe": mpjpe(pred, cases.joints_3d).numpy(),
    }
    if roots is not None:
        errors["mrpe"] = np.linalg.norm(roots - cases.roots, axis=-1)
        placed = pred + roots[:, None]
        truth = cases.joints_3d + cases.roots[:, None]
        errors["camera_mpjpe"] = np.linalg.norm(placed - truth, axis=-1).mean(-1)
    report: dict = {name: float(v.mean()) for name, v in errors.items()}
    report["frames"] = len(cases)
    report["per_action"] = {
        action: {name: float(v[cases.action == action].mean()) for name, v in errors.items()}
        for action in sorted(set(cases.action.tolist()))
    }
    if sets is not None:
        names, counts = np.unique(sets, return_counts=True)
        report["chosen_sets"] = {str(n): int(c) for n, c in zip(names, counts, strict=True)}
    return report


def evaluate(
    lifter, cases: ProtocolCases, noise_px=0.0, outlier_px=0.0, seed=0, batch_size=64, desc="lift"
):
    """The protocol end to end for one input variant: a JSON-ready report."""
    joints_2d = perturb(cases.joints_2d, noise_px, outlier_px, seed)
    pred, roots, sets = lift_all(lifter, cases, joints_2d, batch_size, desc)
    return score(pred, cases, sets, roots)


# Variants of the protocol: (perturbation of the 2D input, LifterConfig overrides).
EVERY_SET = {"partial_sets": "always"}  # the paper: every set scored for every pose
VARIANTS: dict[str, tuple[dict, dict]] = {
    "clean": ({}, {}),
    "noise5": ({"noise_px": 5.0}, {}),
    "noise10": ({"noise_px": 10.0}, {}),
    "outlier40": ({"outlier_px": 40.0}, {}),
    "every-set": ({}, EVERY_SET),
    "every-set-outlier40": ({"outlier_px": 40.0}, EVERY_SET),
    "paper-selection": ({}, {**EVERY_SET, "select_on_all_joints": False}),
    "paper-selection-outlier40": (
        {"outlier_px": 40.0},
        {**EVERY_SET, "select_on_all_joints": False},
    ),
    "unweighted": ({}, UNWEIGHTED_OVERRIDES),
    "database-proportions": ({}, {"proportions": False}),
    "database-proportions-noise10": ({"noise_px": 10.0}, {"proportions": False}),
    "paper": ({}, PAPER_OVERRIDES),
    "paper-noise10": ({"noise_px": 10.0}, PAPER_OVERRIDES),
    "projection-fit-6": ({}, {"projection_iterations": 6}),
    "pose-fit-12": ({}, {"pose_iterations": 12}),
    "nprobe16": ({}, {"nprobe": 16}),
}


def video_report(
    lifter,
    subject: str = TEST_SUBJECT,
    noise_px: float = 10.0,
    frames: int = 500,
    every: int = 6,
    seed: int = 0,
) -> dict:
    """Video: every `every`-th sequence of `subject` (sorted), its first `frames` frames at 50
    fps seen by camera 1 as 2D tracks with `noise_px` of Gaussian noise per coordinate, lifted
    frame by frame with the camera's intrinsics and placed in its coordinates; then the same
    followed as a track (ds3d.people.tracking.follow: One-Euro smoothed, bones held). Per version:
    jitter (mean frame-to-frame acceleration, mm/frame^2), the camera-space MPJPE and the
    MPJPE with hip midpoints aligned, mm."""
    sequences = load_h36m_sequences((subject,))
    camera = load_cameras()[(subject, 1)]
    rng = np.random.default_rng(seed)
    truth, raw = [], []
    for key in sorted(sequences)[::every]:
        poses = sequences[key][:frames]
        joints_2d = camera.project(poses) + rng.normal(0.0, noise_px, (len(poses), NUM_JOINTS, 2))
        k = np.repeat(camera.intrinsics[None], len(poses), 0)
        result = lifter.lift(joints_2d, intrinsics=k)
        assert result.root_position is not None  # placed by the intrinsics
        truth.append(camera.to_camera(poses))
        raw.append((result.joints_3d + result.root_position[:, None]).numpy())

    def figures(clips: list[np.ndarray]) -> dict:
        def mean_of(per_clip) -> float:
            return float(np.mean([per_clip(c, t) for c, t in zip(clips, truth, strict=True)]))

        def centred(x: np.ndarray) -> np.ndarray:
            return x - hip_midpoint(x)[:, None]

        return {
            "jitter": mean_of(lambda c, t: jitter(c)),
            "camera_mpjpe": mean_of(lambda c, t: np.linalg.norm(c - t, axis=-1).mean()),
            "mpjpe": mean_of(lambda c, t: np.linalg.norm(centred(c) - centred(t), axis=-1).mean()),
        }

    return {
        "subject": subject,
        "noise_px": noise_px,
        "sequences": len(raw),
        "frames": sum(len(c) for c in raw),
        "truth_jitter": float(np.mean([jitter(t) for t in truth])),
        "raw": figures(raw),
        "smoothed": figures([follow(c, 50.0) for c in raw]),
    }


def evaluate_variant(lifter, cases: ProtocolCases, name: str, base_config) -> dict:
    """The protocol for one of VARIANTS: the lifter configured as `base_config` (a LifterConfig)
    with the variant's overrides, on the variant's perturbed input. Leaves the lifter so
    configured. Returns evaluate's report with the seconds it took."""
    perturbation, overrides = VARIANTS[name]
    lifter.configure(dataclasses.replace(base_config, **overrides))
    start = time.perf_counter()
    report = evaluate(lifter, cases, **perturbation, desc=name)
    report["seconds"] = round(time.perf_counter() - start, 1)
    return report
