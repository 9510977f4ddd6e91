"""One image's (or video frame's) answer as `ds3d predict` yields, writes and draws it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ds3d.io.sources import Frame
from ds3d.result import Person
from ds3d.viz.overlay import plot


@dataclass
class Prediction:
    """One image's (or video frame's) answer: the frame it came from (source, index, fps,
    image) and its people, best first (one with people="best")."""

    frame: Frame
    people: list[Person]

    @property
    def source(self) -> str:
        return self.frame.source

    @property
    def image(self) -> np.ndarray:
        image = self.frame.image
        assert image is not None, "a prediction is made of a frame that was read"
        return image

    def to_dict(self) -> dict:
        """JSON-ready: source, frame index, image size and every person (Person.to_json)."""
        height, width = self.image.shape[:2]
        return {
            "source": self.source,
            "frame": self.frame.index,
            "width": width,
            "height": height,
            "people": [person.to_json() for person in self.people],
        }

    def plot(self, with_3d: bool = True) -> np.ndarray:
        """The image with every person's 2D skeleton and, with_3d, their 3D skeletons on a
        panel beside it: (H, W [+ 3H/4], 3) uint8 RGB (ds3d.viz.overlay)."""

        def stacked(name: str) -> np.ndarray:  # (N, ...) of every person's field
            return np.array([getattr(person, name) for person in self.people])

        joints_3d = stacked("joints_3d") if with_3d else None
        return plot(self.image, stacked("joints_2d"), joints_3d, stacked("confidence"))
