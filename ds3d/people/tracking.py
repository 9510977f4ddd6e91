"""People followed through a video: each keeps an id from frame to frame (Tracker), and its 3D
joints are smoothed with a filter of bounded lag (OneEuro) and held to the bone lengths seen
along its track (TrackFilter), so that a clip does not jitter and its skeleton does not stretch
(measured by `ds3d eval h36m --video`).

The One-Euro filter (Casiez, Roussel and Vogel, CHI 2012) is a low-pass filter whose cutoff rises
with the signal's speed: still joints are smoothed hard, moving ones follow with little lag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ds3d.boxes import iou
from ds3d.fit.bones import bone_lengths
from ds3d.kinematics import camera_to_world, forward_kinematics, inverse_kinematics
from ds3d.skeleton import hip_midpoint


@dataclass
class OneEuro:
    """A One-Euro filter over arrays of any one shape, one sample per call.

    min_cutoff: Hz, the cutoff of a still signal (lower: smoother, more lag); beta: Hz by which
    the cutoff rises per unit of the signal's speed (per mm/s for joints in mm); d_cutoff: Hz,
    of the speed's own low-pass. Chosen on Human3.6M S9 with 10 px of noise (docs/tuning.md).
    """

    min_cutoff: float = 2.0
    beta: float = 0.0005
    d_cutoff: float = 1.0
    _value: np.ndarray | None = field(default=None, repr=False)
    _speed: np.ndarray | None = field(default=None, repr=False)

    def __call__(self, sample: np.ndarray, dt: float) -> np.ndarray:
        """The filtered value of `sample`, dt s after the previous one."""
        sample = np.asarray(sample, np.float64)
        if self._value is None or self._speed is None:
            self._value, self._speed = sample, np.zeros_like(sample)
            return sample
        speed = (sample - self._value) / dt
        self._speed = _blend(self._speed, speed, _alpha(self.d_cutoff, dt))
        cutoff = self.min_cutoff + self.beta * np.abs(self._speed)
        self._value = _blend(self._value, sample, _alpha(cutoff, dt))
        return self._value


def _alpha(cutoff, dt: float):
    """The smoothing factor of a first-order low-pass of `cutoff` Hz sampled every dt s."""
    tau = 1.0 / (2 * math.pi * np.asarray(cutoff))
    return 1.0 / (1.0 + tau / dt)


def _blend(previous: np.ndarray, sample: np.ndarray, alpha) -> np.ndarray:
    return previous + alpha * (sample - previous)


@dataclass
class TrackFilter:
    """One person's joints along a track, frame by frame: One-Euro smoothed, then held to the
    track's bone lengths (the mean of each bone's length over the frames so far, each bone in
    its smoothed direction: ds3d.kinematics), so that one person keeps one skeleton."""

    smoothing: OneEuro = field(default_factory=OneEuro)
    _length_sum: torch.Tensor | None = field(default=None, repr=False)
    _frames: int = 0

    def __call__(self, joints: np.ndarray, dt: float) -> np.ndarray:
        """(14, 3) mm in camera coordinates, dt s after the previous frame -> the same, held."""
        lengths = bone_lengths(torch.from_numpy(np.asarray(joints, np.float64)))
        self._length_sum = lengths if self._length_sum is None else self._length_sum + lengths
        self._frames += 1
        smoothed = camera_to_world(torch.from_numpy(self.smoothing(joints, dt))[None])
        motion = inverse_kinematics(smoothed, self._length_sum / self._frames)
        return camera_to_world(forward_kinematics(motion))[0].numpy()


def follow(joints: np.ndarray, fps: float, filter: TrackFilter | None = None) -> np.ndarray:
    """(F, 14, 3) one person's joints in camera coordinates, frame by frame at `fps` -> the
    same through a TrackFilter (a new one by default), as a Tracker answers them."""
    track = filter or TrackFilter()
    return np.stack([track(frame, 1.0 / fps) for frame in joints])


def jitter(joints: np.ndarray) -> float:
    """Mean frame-to-frame acceleration, |x_{t+1} - 2 x_t + x_{t-1}| per joint, of (F, J, 3)
    joints (units of the joints per frame squared)."""
    return float(np.linalg.norm(joints[2:] - 2 * joints[1:-1] + joints[:-2], axis=-1).mean())


@dataclass
class _Track:
    id: int
    box: np.ndarray
    joints_2d: np.ndarray
    filter: TrackFilter
    missed: int = 0


class Tracker:
    """Ids for the people of a video's frames, and their 3D joints smoothed along each track.

    A person answered in a frame continues the track whose last box overlaps its own the most
    (IoU at least min_iou), ties broken by the 2D poses' distance (relative to the box's
    diagonal); the others start new tracks. A track not continued for more than max_missed
    frames ends, so that a cut or a person leaving starts afresh. With `smooth`, each track's
    joints in camera coordinates go through its own TrackFilter (with `filter`'s One-Euro
    parameters), and
    the hip-centred joints and the root follow them.
    """

    def __init__(
        self,
        smooth: bool = True,
        filter: OneEuro | None = None,
        min_iou: float = 0.3,
        max_missed: int = 10,
    ):
        self.smooth, self.template = smooth, filter or OneEuro()
        self.min_iou, self.max_missed = min_iou, max_missed
        self.tracks: list[_Track] = []
        self.next_id = 0

    def update(self, people: list, dt: float) -> list:
        """The people of the next frame (ds3d.result.Person, any order), dt s after the last
        one -> the same people with their track_id, their 3D joints smoothed with `smooth`."""
        pairs = []
        if self.tracks and people:
            overlap = iou(np.stack([p.box for p in people]), np.stack([t.box for t in self.tracks]))
            for i, person in enumerate(people):
                for k, track in enumerate(self.tracks):
                    if overlap[i, k] >= self.min_iou:
                        spread = np.linalg.norm(person.box[2:] - person.box[:2]) + 1e-6
                        apart = np.linalg.norm(person.joints_2d - track.joints_2d, axis=-1).mean()
                        pairs.append((overlap[i, k] - apart / spread, i, k))
        track_of: dict[int, _Track] = {}
        taken: set[int] = set()
        for _, i, k in sorted(pairs, reverse=True):
            if i not in track_of and k not in taken:
                track_of[i] = self.tracks[k]
                taken.add(k)
        for k, track in enumerate(self.tracks):
            track.missed = 0 if k in taken else track.missed + 1
        out = []
        for i, person in enumerate(people):
            if i not in track_of:
                follower = TrackFilter(replace(self.template))
                track_of[i] = _Track(self.next_id, person.box, person.joints_2d, follower)
                self.next_id += 1
                self.tracks.append(track_of[i])
            track = track_of[i]
            track.box, track.joints_2d = person.box, person.joints_2d
            out.append(self._followed(person, track, dt))
        self.tracks = [t for t in self.tracks if t.missed <= self.max_missed]
        return out

    def _followed(self, person, track: _Track, dt: float):
        if not self.smooth:
            return replace(person, track_id=track.id)
        placed = track.filter(person.joints_3d_camera, dt).astype(np.float32)
        root = hip_midpoint(placed)
        return replace(person, track_id=track.id, joints_3d=placed - root, root_position=root)
