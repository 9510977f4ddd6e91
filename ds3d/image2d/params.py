"""Parameters of the 2D stage, in two parts: what training fixed (ModelParams: the forests, the
PSM and the networks were grown for these values, so changing them at inference reads the models
wrongly) and what inference may change (InferenceParams: the pyramid, the weights of the
unaries, the speed/accuracy trade-offs). EstimatorParams is both, as the algorithm reads them;
`with_inference` is the one way to change a loaded model's parameters.

How each value was chosen, with the measured effect of the alternatives: docs/tuning.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from ds3d.image2d.psm import local_centroid


@dataclass(frozen=True)
class ModelParams:
    """Fixed by training: the scale the models were grown at and what the cascade's context
    layers read."""

    canonical_extent: float = 100.0  # person extent in px at the working scale
    stride: int = 3  # px between evaluated pixels (one unary cell); the context layers' grid
    context_blur: int = 1  # box radius (cells) on a layer's maps before the next layer reads them
    # Whether a context layer also reads the PSM's MAP pose on the layer before's maps, as one
    # Gaussian heatmap per joint of this sigma (px at the working scale; None: the maps alone).
    context_pose_sigma: float | None = None
    observer_labels: bool = False  # observer-centric cascade + PSM; the facing model decides


SCALE_CHOICES = ("network", "coarse", "every")


@dataclass(frozen=True)
class InferenceParams:
    """What inference may override (`ds3d eval lsp --set NAME=VALUE`)."""

    image_to_extent: float = 1.35  # a full image without a box: its longer side / person extent
    box_to_extent: float = 1.0  # a person box: its longer side / person extent
    box_margin: float = 0.35  # context kept around a box, fraction of the extent per side
    # How far a person box's crop reaches past the image's edge where the box itself does (as a
    # search proposal's does for a person the frame cuts, SearchParams.beyond_edge), as a
    # fraction of the person's extent: black there (zeros to the joint network, which learnt
    # where the joints a photo cuts off lie), so that the PSM places them there rather than
    # squeezing the person into the frame. Only there: a black band beside a tight crop's
    # person costs its pose (docs/tuning.md).
    beyond_edge: float = 0.0
    unary_blur: int = 2  # box radius (cells) on the final maps before the log
    unary_weight: float = 2.0  # the PSM sees unary_weight * unaries (relative to the binaries)
    # Each joint of the PSM's MAP moves to the centroid of its unary probabilities ^ sharpness
    # within this many cells (psm.local_centroid; None: stays on its cell): sub-cell joints.
    centroid_radius: int | None = 2
    centroid_sharpness: float = 4.0
    n_scales: int = 6
    scale_factor: float = 0.85
    scale_start: float = 1.0 / 0.85**2  # the largest pyramid scale, relative to the base
    # How each image's pyramid scale is chosen before the full pass runs on it alone:
    # "network": the extent of the joint network's pose at the base scale (the forests-alone
    # path falls back to "coarse"); "coarse": the best PSM score of a coarse pass of the
    # forests at `select_stride` over every scale; "every": the full pass on every scale, the
    # best PSM score wins.
    scale_choice: str = "network"
    select_stride: int = 6
    coarse_trees: int | None = 8  # trees per layer in the coarse pass (None: all)
    # Trees per layer in the full pass (None: all). Beside the joint network the forests' trees
    # past the fourth added nothing held out (docs/tuning.md, speed).
    trees: int | None = 4
    # Whether the full-stride pass averages each image's class probabilities with its mirror
    # image's (mapped back; the coarse pass never does).
    flip_test: bool = False
    # Weight of the joint network's unaries (ds3d.image2d.jointnet) against the forests' in the
    # final pass of a model that has one (0: the forests alone, as without one).
    jointnet_weight: float = 1.5
    # The forests run only on the cells within this many nats of some joint's best cell in the
    # joint network's unaries (cascade.forest_cells; None: on every cell). Without the network
    # (or with jointnet_weight 0) they run everywhere.
    forest_reach: float | None = 6.0

    def __post_init__(self):
        if self.scale_choice not in SCALE_CHOICES:
            raise ValueError(
                f"scale_choice must be one of {SCALE_CHOICES}, not {self.scale_choice!r}"
            )

    def joint_cells(self, unaries: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
        """Where the joints of a PSM MAP go: unaries (B, 14, H, W) log-probabilities the PSM ran
        on, its MAP cells (B, 14, 2) long (x, y) -> (B, 14, 2) float32 cells (x, y), the local
        unary centroids (psm.local_centroid) or, without a centroid radius, the cells."""
        if self.centroid_radius is None:
            return cells.float()
        return local_centroid(unaries, cells, self.centroid_radius, self.centroid_sharpness)


@dataclass(frozen=True)
class EstimatorParams(InferenceParams, ModelParams):
    """Every parameter of the 2D stage (stored flat in a model's manifest.json)."""

    def with_inference(self, **overrides) -> EstimatorParams:
        """A copy with InferenceParams fields replaced; a ModelParams field (or an unknown
        name) raises ValueError: the models were trained for its value."""
        allowed = inference_fields()
        refused = sorted(set(overrides) - allowed)
        if refused:
            raise ValueError(
                f"not an inference parameter: {', '.join(refused)} "
                f"(those are: {', '.join(sorted(allowed))})"
            )
        return dataclasses.replace(self, **overrides)


def inference_fields() -> set[str]:
    """The names of the fields inference may override."""
    return {f.name for f in dataclasses.fields(InferenceParams)}
