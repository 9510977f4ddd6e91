"""TrainConfig: what `ds3d train-2d` trains. How the values were chosen: docs/tuning.md."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ds3d.image2d.jointnet import JointNetShape


@dataclass
class TrainConfig:
    """What `ds3d train-2d` trains; the defaults are the full model."""

    seed: int = 0
    n_val: int = 300  # last LSP train images held out for validation
    # last LSPet images held out: a second validation set, of other looks; the 2D stage's
    # recipe is chosen by the mean of the two (docs/tuning.md)
    lspet_val: int = 1000
    max_images: int | None = None  # cap on training images (small mode)
    trees: tuple[int, ...] = (16, 16)  # trees per cascade layer
    images_per_tree: int = 4000  # of the ~5,350 in a layer's share (fewer score worse)
    pool_size: int = 512  # random comparisons offered to each tree
    radius: int = 40  # max offset of a comparison, px at the working scale
    pos_per_joint: int = 8
    pos_radius: float = 5.0  # px: pixels this close to a joint are that joint's positives
    facing_epochs: int = 48  # of the facing CNN (ds3d.image2d.facing)
    facing_lr: float = 3e-3  # its peak learning rate (one cycle)
    jointnet_epochs: int = 60  # of the joint network (ds3d.image2d.jointnet); 0: facing CNN
    jointnet_lr: float = 3e-3  # its peak learning rate (one cycle)
    jointnet_widths: tuple[int, int, int] = JointNetShape.widths  # its JointNetShape
    jointnet_blocks: tuple[int, int, int] = JointNetShape.blocks
    # its views degraded (ds3d.training.jointnet.degrade): cut, occluded, blurred, grey
    jointnet_degraded: bool = False
    # the share of its views cut by an image edge, the joints beyond it their targets still
    # (ds3d.training.jointnet.edge_cut)
    jointnet_edge_cut: float = 0.0
    bg_per_image: int = 64
    max_depth: int = 20
    min_samples_leaf: int = 20
    # The paper has 15; 3 scores as well on the held-out images, with a 5x cheaper PSM.
    psm_components: int = 3
    psm_iterations: int = 50

    def jointnet_shape(self) -> JointNetShape:
        (w0, w1, w2), (b0, b1, b2) = self.jointnet_widths, self.jointnet_blocks
        return JointNetShape((w0, w1, w2), (b0, b1, b2))

    @classmethod
    def from_saved(cls, saved: dict) -> TrainConfig:
        """A configuration as a manifest saved it (JSON: tuples came back as lists)."""
        fields: dict[str, Any] = {
            k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()
        }
        return cls(**fields)
