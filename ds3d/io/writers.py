"""What `ds3d predict` writes into its output folder, one prediction at a time:

    predictions.jsonl        always: a line per image or frame (Prediction.to_dict), and a line
                             {"source", "error"} per source that could not be read
    json/NNNNNN_NAME.json    --json: one file per image or frame, numbered in run order
    coco_keypoints.json      --coco: every person in COCO's keypoint format (COCO_FROM_LSP)
    overlay/NNNNNN_NAME.jpg  --overlay: each still image with its 2D skeletons
    NAME_overlay.mp4         --overlay: each video, its frames with the 2D skeletons and the 3D
                             skeletons on a panel beside them
    NAME_3d.npz, NAME_3d.csv each video: the best person's joints per frame, as a sequence
    bvh/NNNNNN_NAME_K.bvh    --bvh: each still image's person K (0: the best) as a one-frame BVH
    NAME_K.bvh               --bvh: each video's tracked person K (ds3d.people.tracking), a
                             frame per frame read from its first to its last (ds3d.kinematics:
                             joint angles, the root where the person stands)

COCO's 17 keypoints from ds3d's 14 LSP joints: the shoulders, elbows, wrists, hips, knees and
ankles map one to one; COCO's nose, eyes and ears have no LSP joint and are written (0, 0)
with visibility 0; LSP's neck and head top have no COCO keypoint and are left out (they are in
predictions.jsonl). A mapped keypoint has visibility 2 where its confidence (the probability that
it lies within PCK@0.2 of the truth, ds3d.confidence) is at least 0.5, else 1 (labelled, likely
off); its confidence is in "keypoint_scores".
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np

from ds3d.data.bvh import format_bvh
from ds3d.io.prediction import Prediction
from ds3d.io.sources import DEFAULT_FPS, Frame
from ds3d.kinematics import camera_motion, to_bvh
from ds3d.skeleton import JOINT_NAMES

COCO_KEYPOINTS = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip
# COCO's limbs, 1-based as its annotations give them
COCO_SKELETON = (
    (16, 14), (14, 12), (17, 15), (15, 13), (12, 13), (6, 12), (7, 13), (6, 7), (6, 8),
    (7, 9), (8, 10), (9, 11), (2, 3), (1, 2), (1, 3), (2, 4), (3, 5), (4, 6), (5, 7),
)  # fmt: skip
VISIBLE_CONFIDENCE = 0.5  # COCO's v = 2 (visible) from this confidence on, else 1
# For each COCO keypoint, the LSP joint (ds3d.skeleton.JOINT_NAMES index) or None.
COCO_FROM_LSP = tuple(
    JOINT_NAMES.index(name) if name in JOINT_NAMES else None for name in COCO_KEYPOINTS
)


def coco_keypoints(joints_2d: np.ndarray, confidence: np.ndarray) -> tuple[list, list]:
    """(14, 2) px and (14,) -> COCO's flat [x, y, v] * 17 and its 17 keypoint scores; v is 2
    for a confidence of at least VISIBLE_CONFIDENCE, else 1."""
    flat, scores = [], []
    for joint in COCO_FROM_LSP:
        if joint is None:
            flat += [0.0, 0.0, 0]
            scores.append(0.0)
        else:
            sure = float(confidence[joint])
            visible = 2 if sure >= VISIBLE_CONFIDENCE else 1
            flat += [round(float(joints_2d[joint, 0]), 2), round(float(joints_2d[joint, 1]), 2)]
            flat.append(visible)
            scores.append(round(sure, 4))
    return flat, scores


class RunWriter:
    """Writes a run's outputs into `folder` (see the module's docstring); use as a context
    manager, or call close() to finish the files that span the run."""

    def __init__(
        self,
        folder: Path,
        json_files: bool = False,
        coco: bool = False,
        overlay: bool = False,
        stride: int = 1,
        bvh: bool = False,
    ):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.lines = open(self.folder / "predictions.jsonl", "w")  # closed by close()
        self.json_files, self.overlay, self.bvh = json_files, overlay, bvh
        self.coco: dict[str, list[dict]] | None = (
            {"images": [], "annotations": []} if coco else None
        )
        self.count = 0
        self.stride = stride  # of the videos' frames: the overlay MP4 plays at fps / stride
        self.video: _VideoOutputs | None = None

    def __enter__(self) -> RunWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def skip(self, frame: Frame) -> None:
        self.lines.write(json.dumps({"source": frame.source, "error": frame.error}) + "\n")

    def write(self, prediction: Prediction) -> None:
        record = prediction.to_dict()
        self.lines.write(json.dumps(record) + "\n")
        self.count += 1
        name = f"{self.count:06d}_{prediction.frame.name}"
        if self.json_files:
            (self.folder / "json").mkdir(exist_ok=True)
            (self.folder / "json" / f"{name}.json").write_text(json.dumps(record, indent=1))
        if self.coco is not None:
            self._add_coco(self.coco, prediction, name)
        is_video = prediction.frame.index is not None
        if self.video is not None and (not is_video or self.video.source != prediction.source):
            self.video.close()
            self.video = None
        if is_video:
            if self.video is None:
                self.video = _VideoOutputs(
                    self.folder, prediction.frame, self.overlay, self.stride, self.bvh
                )
            self.video.add(prediction)
            return
        if self.overlay:
            (self.folder / "overlay").mkdir(exist_ok=True)
            picture = prediction.plot(with_3d=False)
            cv2.imwrite(str(self.folder / "overlay" / f"{name}.jpg"), picture[..., ::-1])
        if self.bvh:
            (self.folder / "bvh").mkdir(exist_ok=True)
            for k, person in enumerate(prediction.people):
                text = bvh_text(person.joints_3d_camera[None], frame_time=1.0)
                (self.folder / "bvh" / f"{name}_{k}.bvh").write_text(text)

    def _add_coco(self, coco: dict[str, list[dict]], prediction: Prediction, name: str) -> None:
        image_id = self.count
        height, width = prediction.image.shape[:2]
        coco["images"].append(
            {
                "id": image_id,
                "file_name": prediction.source,
                "frame": prediction.frame.index,
                "width": width,
                "height": height,
            }
        )
        for person in prediction.people:
            keypoints, scores = coco_keypoints(person.joints_2d, person.confidence)
            x0, y0, x1, y1 = (float(v) for v in person.box)
            coco["annotations"].append(
                {
                    "id": len(coco["annotations"]) + 1,
                    "image_id": image_id,
                    "category_id": 1,
                    "keypoints": keypoints,
                    "num_keypoints": 12,
                    "keypoint_scores": scores,
                    "bbox": [round(x0, 2), round(y0, 2), round(x1 - x0, 2), round(y1 - y0, 2)],
                    "area": round((x1 - x0) * (y1 - y0), 2),
                    "iscrowd": 0,
                    "score": round(person.score, 4),
                }
            )

    def close(self) -> None:
        if self.video is not None:
            self.video.close()
            self.video = None
        self.lines.close()
        if self.coco is not None:
            category = {
                "id": 1,
                "name": "person",
                "supercategory": "person",
                "keypoints": list(COCO_KEYPOINTS),
                "skeleton": COCO_SKELETON,
            }
            coco = {
                "info": {"description": "ds3d predictions"},
                "categories": [category],
                **self.coco,
            }
            (self.folder / "coco_keypoints.json").write_text(json.dumps(coco))


def bvh_text(joints: np.ndarray, frame_time: float) -> str:
    """A BVH file of one person's F poses (F, 14, 3) mm in camera coordinates: its joint angles
    (ds3d.kinematics) with the bones' median lengths, the root where the person stands."""
    return format_bvh(to_bvh(camera_motion(joints), frame_time))


class _VideoOutputs:
    """One video's sequence (NAME_3d.npz, NAME_3d.csv), with overlay NAME_overlay.mp4, with bvh
    NAME.bvh."""

    def __init__(self, folder: Path, first: Frame, overlay: bool, stride: int, bvh: bool = False):
        self.source = first.source
        stem = Path(first.source.split("?")[0]).stem or "video"
        self.base = folder / stem.replace(":", "")
        self.fps = first.fps or DEFAULT_FPS
        self.frames: list[int] = []
        self.joints_3d: list[np.ndarray] = []
        # per track, the frame (of those read) and joints_3d_camera of each of its people
        self.tracks: dict[int, list[tuple[int, np.ndarray]]] = {}
        self.bvh = bvh
        self.joints_2d: list[np.ndarray] = []
        self.scores: list[float] = []
        self.writer: cv2.VideoWriter | None = None
        self.overlay, self.stride = overlay, stride

    def add(self, prediction: Prediction) -> None:
        index = prediction.frame.index
        assert index is not None, "a video's frames are numbered"
        self.frames.append(index)
        for person in prediction.people:
            if person.track_id is not None:
                self.tracks.setdefault(person.track_id, []).append(
                    (len(self.frames) - 1, person.joints_3d_camera)
                )
        if prediction.people:  # the best person; NaN for a frame with nobody
            best = prediction.people[0]
            self.joints_3d.append(best.joints_3d)
            self.joints_2d.append(best.joints_2d)
            self.scores.append(best.score)
        else:
            self.joints_3d.append(np.full((len(JOINT_NAMES), 3), np.nan, np.float32))
            self.joints_2d.append(np.full((len(JOINT_NAMES), 2), np.nan, np.float32))
            self.scores.append(0.0)
        if self.overlay:
            picture = prediction.plot(with_3d=True)[..., ::-1]
            if self.writer is None:
                size = (picture.shape[1], picture.shape[0])
                path = f"{self.base}_overlay.mp4"
                self.writer = cv2.VideoWriter(
                    path, cv2.VideoWriter.fourcc(*"mp4v"), self.fps / self.stride, size
                )
            self.writer.write(np.ascontiguousarray(picture))

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()
        for track, seen in self.tracks.items() if self.bvh else ():
            # from the track's first frame to its last; a frame it missed holds the pose before
            at = np.array([k for k, _ in seen])
            held = np.searchsorted(at, np.arange(at[0], at[-1] + 1), side="right") - 1
            poses = np.stack([pose for _, pose in seen])[held]
            Path(f"{self.base}_{track}.bvh").write_text(bvh_text(poses, self.stride / self.fps))
        joints_3d = np.stack(self.joints_3d)
        np.savez_compressed(
            f"{self.base}_3d.npz",
            frame=np.array(self.frames),
            fps=self.fps,
            joints_3d=joints_3d,
            joints_2d=np.stack(self.joints_2d),
            score=np.array(self.scores, np.float32),
            joint_names=np.array(JOINT_NAMES),
        )
        with open(f"{self.base}_3d.csv", "w", newline="") as f:
            out = csv.writer(f)
            out.writerow(["frame", "time_s", "joint", "x_mm", "y_mm", "z_mm"])
            for frame, pose in zip(self.frames, joints_3d, strict=True):
                for name, (x, y, z) in zip(JOINT_NAMES, pose, strict=True):
                    out.writerow(
                        [
                            frame,
                            round(frame / self.fps, 4),
                            name,
                            round(float(x), 2),
                            round(float(y), 2),
                            round(float(z), 2),
                        ]
                    )
