"""ds3d.Lifter: 2D poses in, 3D poses out, by the 3D stage of the paper (Section 4).

    retrieval      K neighbours per joint set from the pose database        (ds3d.mocap.retrieval)
    projection fit M_s per set, eq:projerr1, batched L-BFGS                  (ds3d.fit.solve)
    weighting      keep the K_w best neighbours, eq:wtn                     (ds3d.fit.selection)
    set choice     s^ by eq:energyS, E_p on all visible joints              (ds3d.fit.selection)
    3D fit         X^ by eq:energyMin2 over PCA(18) of the neighbours       (ds3d.fit.solve)

With no image there are no unaries, so a neighbour's weight (eq:wt) is replaced by the negative
of its own 2D fit residual E_p under M_s: the neighbours that project best onto the 2D pose count
most. ds3d.Pipeline passes image-based scores instead.

Each stage is a public method that ds3d.Pipeline composes too: `query` (checked input and its
camera frame), `neighbours` (`retrieve` + `fit_projections`), `weight_neighbours`, `choose_set`,
`fit_pose`.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ds3d.fit.bones import bone_lengths
from ds3d.fit.camera import CameraFrame, image_frame, project, rotation_matrix
from ds3d.fit.energy import projection_energy
from ds3d.fit.selection import set_energy, top_weighted
from ds3d.fit.solve import EnergyWeights, fit_pose, fit_projection
from ds3d.inputs import intrinsics_batch, joints_2d_batch, visibility_batch
from ds3d.mocap.database import PoseDatabase
from ds3d.mocap.retrieval import IndexConfig, PoseRetriever, database_digest
from ds3d.paths import MODELS_DIR
from ds3d.skeleton import SET_NAMES, hip_midpoint, joint_set_mask
from ds3d.timing import stage_timer


@dataclass(frozen=True)
class LifterConfig:
    """Algorithm parameters; the defaults are the paper's (K, K_w, PCA, omegas)."""

    neighbours: int = 256  # K
    nprobe: int = 8  # IVF lists searched: near-exact neighbours (docs/RESULTS.md, retrieval)
    weighted_neighbours: int = 64  # K_w; equal to K for the unweighted variant
    weighting: bool = True  # False: all K neighbours with weight 1 (the paper's ablation)
    pca_components: int = 18
    joint_sets: tuple[str, ...] = SET_NAMES  # ("all",) for the single-set ablation
    omega: EnergyWeights = field(default_factory=EnergyWeights)
    # eq:projerr1 on the nearest neighbours only: M is six numbers, which a few dozen poses
    # seen from nearly the same view pin down as well as all K
    projection_neighbours: int = 32
    projection_iterations: int = 2  # Gauss-Newton steps of eq:projerr1
    pose_iterations: int = 4  # Gauss-Newton steps of eq:energyMin2
    proportions: bool = True  # estimate the person's bone-group scales (False: the database's)
    # eq:energyS scores each set's neighbours by E_p on all visible joints; False: on the set's
    # own joints, as written, which lets small sets win by fitting fewer joints.
    select_on_all_joints: bool = True
    # "hidden": the sets other than `all` are scored only for poses with a hidden joint (with
    # every joint visible `all` is as good: docs/RESULTS.md, the joint-set ablation); "always":
    # every set for every pose, as the paper.
    partial_sets: str = "hidden"
    index: IndexConfig = field(default_factory=IndexConfig)


@dataclass(frozen=True)
class Query:
    """A batch of 2D poses as the stages take them: joints_2d (B, 14, 2) px, visible (B, 14)
    bool, and the projection model's fixed frame (ds3d.fit.camera.image_frame)."""

    joints_2d: torch.Tensor
    visible: torch.Tensor
    frame: CameraFrame

    def take(self, rows: torch.Tensor) -> Query:
        """The poses `rows` (index into B)."""
        return Query(self.joints_2d[rows], self.visible[rows], self.frame.take(rows))

    def moved_to(self, joints_2d: torch.Tensor) -> Query:
        """The same query with other 2D joints and the same frame (the pipeline's iterations:
        warm-started projections stay in the first frame's coordinates)."""
        return Query(joints_2d, self.visible, self.frame)


@dataclass
class Neighbours:
    """What retrieval and the projection fit found: poses (B, S, K, 14, 3) mm, camera-oriented;
    params (B, S, 6), the projection M_s of each set; residuals (B, S, K), each neighbour's
    eq:projerr1 energy under it."""

    poses: torch.Tensor
    params: torch.Tensor
    residuals: torch.Tensor


@dataclass
class LiftResult:
    """joints_3d: (B, 14, 3) float32 mm, camera-oriented (x right, y down, z away from the
    camera), root at the hip midpoint. bone_lengths: (B, 14) mm, ds3d.skeleton.BONE_NAMES order,
    the person's (LifterConfig.proportions) or the database's. joint_set: the chosen set per
    pose. energy: (B,) the chosen set's eq:energyS value. set_energies: (B, S), sets in
    `set_names` order, inf for a set not scored (LifterConfig.partial_sets). projection:
    (B, 6) M^ (ds3d.fit.camera). timings_ms: wall time of each stage for the whole batch."""

    joints_3d: torch.Tensor
    bone_lengths: torch.Tensor
    joint_set: list[str]
    energy: torch.Tensor
    set_energies: torch.Tensor
    projection: torch.Tensor
    timings_ms: dict[str, float]
    set_names: tuple[str, ...] = SET_NAMES


class Lifter:
    """Load once, lift many: `Lifter.load().lift(joints_2d, visible, intrinsics)`."""

    def __init__(
        self,
        database: PoseDatabase,
        config: LifterConfig = LifterConfig(),
        device: str | torch.device = "cpu",
        cache_indices: bool = True,
    ):
        self.device = torch.device(device)
        self.database = database
        self.retriever = PoseRetriever(database, config.index, cache=cache_indices)
        self.database.poses = self.database.poses.to(self.device)
        self.database.rotations = self.database.rotations.to(self.device)
        self.configure(config)
        self.model_id = f"{database.manifest.get('source', 'posedb')}-{database_digest(database)}"

    def configure(self, config: LifterConfig) -> None:
        """Change the algorithm parameters (not the index) of a loaded lifter."""
        if config.index != self.retriever.config:
            raise ValueError("the index settings are fixed when a Lifter is built")
        self.config = config
        self._views: dict[tuple[str, ...], Lifter] = {}  # _restricted's, for this config
        self.set_ids = [SET_NAMES.index(name) for name in config.joint_sets]
        masks = torch.from_numpy(joint_set_mask())  # (5, 14), SET_NAMES order
        self.set_masks = masks[self.set_ids].to(self.device)  # (S, 14)

    @classmethod
    def load(
        cls,
        model_dir: str | Path | None = None,
        device: str = "cpu",
        config: LifterConfig = LifterConfig(),
        database: str = "posedb",
    ) -> Lifter:
        """The pose database `model_dir`/`database` (default: models/posedb, from Human3.6M;
        models/posedb-cmu holds the CMU one)."""
        directory = Path(model_dir) if model_dir is not None else MODELS_DIR
        return cls(PoseDatabase.load(directory / database), config, device)

    def lift(self, joints_2d, visible=None, intrinsics=None) -> LiftResult:
        """joints_2d: (B, 14, 2) px, LSP order; visible: optional (B, 14) bool; intrinsics:
        optional (B, 3, 3) (without: weak perspective). Raises ds3d.errors.InvalidPose.
        With config.partial_sets "hidden", a pose whose joints are all visible is lifted with
        the set `all` alone, the others with every configured set."""
        query = self.query(joints_2d, visible, intrinsics)
        complete = query.visible.all(-1)
        if self.config.partial_sets == "always" or "all" not in self.config.joint_sets:
            complete = torch.zeros_like(complete)
        parts, rows = [], []
        for take, lifter in ((complete, self._restricted(("all",))), (~complete, self)):
            if bool(take.any()):
                rows.append(take.nonzero()[:, 0])
                parts.append(lifter._lift(query.take(rows[-1])))
        return self._merge(parts, rows)

    def _restricted(self, joint_sets: tuple[str, ...]) -> Lifter:
        """This lifter (the same database and indices) scoring only `joint_sets`."""
        if joint_sets not in self._views:
            view = copy.copy(self)
            view.configure(dataclasses.replace(self.config, joint_sets=joint_sets))
            self._views[joint_sets] = view
        return self._views[joint_sets]

    def _merge(self, parts: list[LiftResult], rows: list[torch.Tensor]) -> LiftResult:
        """Results of lifting the disjoint rows of one batch, as one LiftResult in batch order,
        energies of every configured set (inf for a set a part did not score)."""
        order = torch.cat(rows).argsort().cpu()
        names = self.config.joint_sets
        set_energies = []
        for part in parts:
            full = torch.full((len(part.energy), len(names)), torch.inf)
            scored = [names.index(n) for n in part.set_names]
            full[:, scored] = part.set_energies
            set_energies.append(full)
        timings: dict[str, float] = {}
        for part in parts:
            for stage, ms in part.timings_ms.items():
                timings[stage] = timings.get(stage, 0.0) + ms
        sets = [s for part in parts for s in part.joint_set]
        return LiftResult(
            joints_3d=torch.cat([p.joints_3d for p in parts])[order],
            bone_lengths=torch.cat([p.bone_lengths for p in parts])[order],
            joint_set=[sets[i] for i in order.tolist()],
            energy=torch.cat([p.energy for p in parts])[order],
            set_energies=torch.cat(set_energies)[order],
            projection=torch.cat([p.projection for p in parts])[order],
            timings_ms=timings,
            set_names=names,
        )

    def _lift(self, query: Query) -> LiftResult:
        """Every stage on every configured set."""
        timings: dict[str, float] = {}
        found = self.neighbours(query, timings=timings)
        with torch.no_grad(), stage_timer(timings, "selection", self.device):
            kept, weights, kept_residuals = self.weight_neighbours(found.poses, -found.residuals)
            energies, best = self.choose_set(kept, weights, kept_residuals, found.params, query)
        with torch.no_grad(), stage_timer(timings, "pose_fit", self.device):
            pose, projection = self.fit_pose(kept, weights, found.params, query, best)
        rows = torch.arange(len(best), device=self.device)
        return LiftResult(
            joints_3d=pose.cpu(),
            bone_lengths=bone_lengths(pose).cpu(),
            joint_set=[self.config.joint_sets[i] for i in best.tolist()],
            energy=energies[rows, best].cpu(),
            set_energies=energies.cpu(),
            projection=projection.cpu(),
            timings_ms=timings,
            set_names=self.config.joint_sets,
        )

    def query(self, joints_2d, visible=None, intrinsics=None) -> Query:
        """Checked 2D input on the lifter's device, with its camera frame. Arguments as lift;
        raises ds3d.errors.InvalidPose."""
        x = joints_2d_batch(joints_2d).to(self.device)
        vis = visibility_batch(visible, len(x)).to(self.device)
        k = intrinsics_batch(intrinsics, len(x))
        return Query(x, vis, image_frame(x, vis, None if k is None else k.to(self.device)))

    def neighbours(
        self,
        query: Query,
        start: torch.Tensor | None = None,
        timings: dict[str, float] | None = None,
    ) -> Neighbours:
        """Retrieval and projection fit (eq:projerr1): K neighbours per configured set and the
        projection M_s of each set fitted to them. start: optional (B, S, 6) projections to
        start the fit from (a previous iteration's). Adds the stages' ms to `timings`."""
        timings = {} if timings is None else timings
        with torch.no_grad(), stage_timer(timings, "retrieval", self.device):
            poses = self.retrieve(query.joints_2d)
        with stage_timer(timings, "projection_fit", self.device):
            params, residuals = self.fit_projections(poses, query, start)
        return Neighbours(poses, params, residuals)

    def retrieve(self, joints_2d: torch.Tensor) -> torch.Tensor:
        """K neighbours per configured set, camera-oriented. joints_2d: (B, 14, 2) px.
        Returns (B, S, K, 14, 3) mm."""
        ids = self.retriever.search(
            joints_2d, self.config.neighbours, self.config.nprobe, self.config.joint_sets
        )
        return self.database.candidates(ids.to(self.device))

    def choose_set(self, kept, weights, kept_residuals, params, query: Query):
        """s^ by eq:energyS. kept: (B, S, K_w, 14, 3); weights, kept_residuals: (B, S, K_w);
        params: (B, S, 6). Returns the energies (B, S) and the chosen set (B,) among the usable
        ones."""
        if self.config.select_on_all_joints:
            kept_residuals = projection_energy(
                project(kept, params, query.frame.unsqueeze(1)),
                query.joints_2d[:, None],
                query.visible[:, None].float(),
            )
        energies = set_energy(kept, weights, kept_residuals, self.config.omega)
        usable = self.usable_sets(query.visible)
        return energies, torch.where(usable, energies, torch.inf).argmin(-1)

    def usable_sets(self, visible: torch.Tensor) -> torch.Tensor:
        """(B, S) bool: a set with a hidden joint only counts when every set has one."""
        masks = self.set_masks * visible[:, None].float()
        complete = (masks == self.set_masks).all(-1)
        return complete | ~complete.any(-1, keepdim=True)

    def fit_pose(self, kept, weights, params, query: Query, best):
        """eq:energyMin2 on the chosen set `best` (B,) of each pose. kept: (B, S, K_w, 14, 3);
        weights: (B, S, K_w); params: (B, S, 6). Returns the pose (B, 14, 3) mm,
        camera-oriented, root at the hip midpoint, with the person's proportions, and its
        projection (B, 6)."""
        rows = torch.arange(len(best), device=best.device)
        pose, projection = fit_pose(
            kept[rows, best],
            weights[rows, best],
            params[rows, best],
            query.joints_2d,
            self.set_masks[best] * query.visible.float(),
            query.frame,
            self.config.omega,
            self.config.pca_components,
            self.config.pose_iterations,
            self.config.proportions,
        )
        oriented = pose @ rotation_matrix(projection[:, :3]).transpose(-1, -2)
        return oriented - hip_midpoint(oriented)[:, None], projection

    def fit_projections(self, candidates, query: Query, start=None):
        """eq:projerr1 for every (pose, set), all B * S problems in one solve on all 14 joints,
        each set's own masked, on the set's `projection_neighbours` nearest neighbours.
        candidates: (B, S, K, 14, 3); start: optional (B, S, 6). Returns params (B, S, 6) and
        the residuals of all K neighbours under them (B, S, K)."""
        b, n_sets = candidates.shape[:2]
        masks = self.set_masks[None] * query.visible[:, None].float()  # (B, S, 14)
        params = fit_projection(
            candidates[:, :, : self.config.projection_neighbours].flatten(0, 1),
            query.joints_2d.repeat_interleave(n_sets, 0),
            masks.flatten(0, 1),
            query.frame.repeat(n_sets),
            None if start is None else start.flatten(0, 1),
            self.config.projection_iterations,
        ).view(b, n_sets, -1)
        projected = project(candidates, params, query.frame.unsqueeze(1))
        return params, projection_energy(projected, query.joints_2d[:, None], masks)

    def weight_neighbours(self, candidates, scores):
        """eq:wt/eq:wtn. candidates: (B, S, K, 14, 3); scores: (B, S, K), higher is better.
        Returns the kept neighbours (B, S, K_w, 14, 3), weights (B, S, K_w) and their -scores."""
        if not self.config.weighting:
            return candidates, torch.ones_like(scores), -scores
        index, weights = top_weighted(scores, self.config.weighted_neighbours)
        kept = torch.take_along_dim(candidates, index[..., None, None], dim=2)
        return kept, weights, -torch.take_along_dim(scores, index, dim=2)
