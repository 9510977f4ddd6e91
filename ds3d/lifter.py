"""ds3d.Lifter: 2D poses in, 3D poses out, by the 3D stage of the paper (Section 4).

    retrieval      K neighbours per joint set from the pose database        (ds3d.mocap.retrieval)
    projection fit M_s per set, eq:projerr1, batched Gauss-Newton            (ds3d.fit.solve)
    weighting      keep the K_w best neighbours, eq:wtn                     (ds3d.fit.selection)
    set choice     s^ by eq:energyS, E_p on all visible joints              (ds3d.fit.selection)
    3D fit         X^ by eq:energyMin2 over PCA(18) of the neighbours       (ds3d.fit.solve)
    learnt prior   a pose lifted by networks learnt from the database: the   (ds3d.mocap.prior)
                   3D fit's start, one more direction and E_l (not in the paper)

With no image there are no unaries, so a neighbour's weight (eq:wt) is replaced by the negative
of its own 2D fit residual E_p under M_s: the neighbours that project best onto the 2D pose count
most. ds3d.Pipeline passes image-based scores instead.

Every stage works on (pose, joint set) problems (Problems), and each is a public method that
ds3d.Pipeline composes too: `query` (checked input and its camera frame), `problems` (which
sets of which poses), `neighbours` (`retrieve` + `fit_projections`), `weight_neighbours`,
`set_energies`, `choose`, `fit_pose`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ds3d.errors import DataFormatError
from ds3d.fit.bones import bone_lengths
from ds3d.fit.camera import (
    CameraFrame,
    camera_translation,
    image_frame,
    project,
    rotation_matrix,
)
from ds3d.fit.energy import projection_energy
from ds3d.fit.selection import set_energy, top_weighted
from ds3d.fit.solve import EnergyWeights, fit_pose, fit_projection
from ds3d.inputs import PoseInput, intrinsics_batch, joints_2d_batch, visibility_batch
from ds3d.mocap.database import PoseDatabase
from ds3d.mocap.prior import PRIOR_DIR, LiftingPrior
from ds3d.mocap.retrieval import IndexConfig, PoseRetriever, database_digest
from ds3d.skeleton import SET_NAMES, hip_midpoint, joint_set_mask
from ds3d.util.groups import group_rows
from ds3d.util.paths import MODELS_DIR, require_models
from ds3d.util.timing import stage_timer


@dataclass(frozen=True)
class LifterConfig:
    """Algorithm parameters: the paper's K and omegas; the PCA's size and the prior on the
    proportions chosen by leave-one-subject-out on the training subjects, K_w on S9 with the
    learnt prior (docs/tuning.md; the paper's K_w = 64 and 18 components: PAPER_OVERRIDES)."""

    # K: the paper's 256 (PAPER_OVERRIDES); with the learnt prior 128 are as good on S9 and the
    # lift faster (docs/tuning.md)
    neighbours: int = 128
    nprobe: int = 8  # IVF lists searched: near-exact neighbours (docs/RESULTS.md, retrieval)
    # K_w; equal to K for the unweighted variant. With the learnt prior 64 are as good as 128 and
    # faster; without it 128 are steadier (S1, S5-S9 left out in turn: docs/tuning.md)
    weighted_neighbours: int = 64
    weighting: bool = True  # False: all K neighbours with weight 1 (the paper's ablation)
    pca_components: int = 20
    joint_sets: tuple[str, ...] = SET_NAMES  # ("all",) for the single-set ablation
    omega: EnergyWeights = field(default_factory=EnergyWeights)
    # eq:projerr1 on the nearest neighbours only: M is six numbers, which a few dozen poses
    # seen from nearly the same view pin down as well as all K
    projection_neighbours: int = 32
    projection_iterations: int = 1  # Gauss-Newton steps of eq:projerr1
    pose_iterations: int = 4  # Gauss-Newton steps of eq:energyMin2
    proportions: bool = True  # estimate the person's bone-group scales (False: the database's)
    # eq:energyS scores each set's neighbours by E_p on all visible joints; False: on the set's
    # own joints, as written, which lets small sets win by fitting fewer joints.
    select_on_all_joints: bool = True
    # "needed": each pose scores only the sets it could choose: `all` when every joint is
    # visible (the others are no better then: docs/RESULTS.md, the joint-set ablation), else the
    # sets without a hidden joint; "always": every set for every pose, as the paper.
    partial_sets: str = "needed"
    # eq:energyS's pairwise terms (E_r, E_a of each neighbour against the others) on the best
    # weighted this many of the K_w: their cost grows as the square of the neighbours
    selection_neighbours: int = 64
    index: IndexConfig = field(default_factory=IndexConfig)
    # Off the CPU, search the indices' lists on the lifter's device (mocap.retrieval.DeviceLists:
    # the same neighbours, no round trip); False: faiss on the CPU there too.
    retrieval_on_device: bool = True
    # The database's learnt lifting prior (ds3d.mocap.prior), where it has one, in the 3D fit:
    # its pose is the fit's start and one more direction to move along, and E_l (weight
    # omega.learnt) holds the person near it. False: the neighbours alone, as the paper.
    prior: bool = True


# The paper's algorithm without ds3d's departures for speed, accuracy and proportions, the
# ablations' reference: every set scored for every pose, the projection fitted to all K
# neighbours, K_w = 64, 18 components, the database's proportions, no learnt prior.
# dataclasses.replace(LifterConfig(), **PAPER_OVERRIDES).
PAPER_OVERRIDES = {
    "neighbours": 256,
    "partial_sets": "always",
    "projection_neighbours": 256,
    "weighted_neighbours": 64,
    "pca_components": 18,
    "proportions": False,
    "prior": False,
}


# The paper's ablation without the weighting: its K = 256 neighbours, each of weight 1, and
# eq:energyS on all of them.
UNWEIGHTED_OVERRIDES = {"weighting": False, "neighbours": 256, "selection_neighbours": 256}


@dataclass(frozen=True)
class Query:
    """A batch of 2D poses as the stages take them: joints_2d (B, 14, 2) px, visible (B, 14)
    bool, and the projection model's fixed frame (ds3d.fit.camera.image_frame)."""

    joints_2d: torch.Tensor
    visible: torch.Tensor
    frame: CameraFrame

    @classmethod
    def of(
        cls, joints_2d: torch.Tensor, visible: torch.Tensor, intrinsics: torch.Tensor | None
    ) -> Query:
        """The query of 2D poses already checked (ds3d.inputs), with its frame, on their
        device: joints_2d (B, 14, 2) px, visible (B, 14) bool, intrinsics None or (B, 3, 3)."""
        return cls(joints_2d, visible, image_frame(joints_2d, visible, intrinsics))

    def take(self, rows: torch.Tensor) -> Query:
        """The poses `rows` (index into B)."""
        return Query(self.joints_2d[rows], self.visible[rows], self.frame.take(rows))

    def moved_to(self, joints_2d: torch.Tensor) -> Query:
        """The same query with other 2D joints and the same frame (the pipeline's iterations:
        warm-started projections stay in the first frame's coordinates)."""
        return Query(joints_2d, self.visible, self.frame)


@dataclass(frozen=True)
class Problems:
    """P (pose, joint set) problems of a query, the unit every stage works on: query, the B
    poses; pose (P,) long, the pose of each problem; joint_set (P,) long, its set (an index into
    LifterConfig.joint_sets); own, the P problems' poses (query.take(pose)); masks (P, 14)
    float, the set's joints that are visible. On the lifter's device."""

    query: Query
    pose: torch.Tensor
    joint_set: torch.Tensor
    own: Query
    masks: torch.Tensor

    def take(self, rows: torch.Tensor) -> Problems:
        """The problems `rows` (index into P)."""
        return Problems(
            self.query, self.pose[rows], self.joint_set[rows], self.own.take(rows), self.masks[rows]
        )


@dataclass
class Neighbours:
    """What retrieval and the projection fit found for P problems: poses (P, K, 14, 3) mm,
    camera-oriented; params (P, 6), the projection M_s of each; residuals (P, K), each
    neighbour's eq:projerr1 energy under it."""

    poses: torch.Tensor
    params: torch.Tensor
    residuals: torch.Tensor


@dataclass(frozen=True)
class LiftedPose:
    """One pose lifted (a row of LiftResult): joints_3d (14, 3) float32 mm, bone_lengths (14,)
    float32 mm, joint_set, energy, root_position (3,) float32 mm or None where no camera placed
    it."""

    joints_3d: np.ndarray
    bone_lengths: np.ndarray
    joint_set: str
    energy: float
    root_position: np.ndarray | None

    def to_json(self) -> dict:
        """JSON-ready: every field, arrays as lists."""
        return {
            f.name: value.tolist() if isinstance(value, np.ndarray) else value
            for f in dataclasses.fields(self)
            for value in [getattr(self, f.name)]
        }


@dataclass
class LiftResult:
    """joints_3d: (B, 14, 3) float32 mm, camera-oriented (x right, y down, z away from the
    camera), root at the hip midpoint. bone_lengths: (B, 14) mm, ds3d.skeleton.BONE_NAMES order,
    the person's (LifterConfig.proportions) or the database's. joint_set: the chosen set per
    pose. energy: (B,) the chosen set's eq:energyS value. set_energies: (B, S), inf for a set
    not scored (LifterConfig.partial_sets). projection: (B, 6) M^ (ds3d.fit.camera).
    root_position: (B, 3) float32 mm, the hip midpoint in camera coordinates (joints_3d +
    root_position: the joints there), placed by M^ (ds3d.fit.camera.camera_translation) with
    the intrinsics given, or else the `camera` given; NaN rows for poses without either, None
    where no pose had one. timings_ms: wall time of each stage for the whole batch."""

    joints_3d: torch.Tensor
    bone_lengths: torch.Tensor
    joint_set: list[str]
    energy: torch.Tensor
    set_energies: torch.Tensor
    projection: torch.Tensor
    root_position: torch.Tensor | None
    timings_ms: dict[str, float]

    def pose(self, i: int) -> LiftedPose:
        """Pose i (of the B)."""
        root = None if self.root_position is None else self.root_position[i]
        return LiftedPose(
            self.joints_3d[i].numpy(),
            self.bone_lengths[i].numpy(),
            self.joint_set[i],
            float(self.energy[i]),
            None if root is None or bool(root.isnan().any()) else root.numpy(),
        )

    @classmethod
    def gather(cls, parts: Sequence[tuple[list[int], LiftResult]]) -> LiftResult:
        """One result of poses lifted in parts: (rows, the result of those poses), the rows of
        all parts together 0..B-1. Each stage's timings_ms are summed over the parts."""
        order = torch.tensor([row for rows, _ in parts for row in rows]).argsort()
        results = [part for _, part in parts]

        def cat(name: str) -> torch.Tensor:
            return torch.cat([getattr(r, name) for r in results])[order]

        roots = None
        if any(r.root_position is not None for r in results):
            roots = torch.cat(
                [
                    torch.full((len(r.energy), 3), torch.nan)
                    if r.root_position is None
                    else r.root_position
                    for r in results
                ]
            )[order]
        stages = {k: None for r in results for k in r.timings_ms}
        return cls(
            joints_3d=cat("joints_3d"),
            bone_lengths=cat("bone_lengths"),
            joint_set=[name for r in results for name in r.joint_set],
            energy=cat("energy"),
            set_energies=cat("set_energies"),
            projection=cat("projection"),
            root_position=roots,
            timings_ms={k: sum(r.timings_ms.get(k, 0.0) for r in results) for k in stages},
        )


class Lifter:
    """Load once, lift many: `Lifter.load().lift(joints_2d, visible, intrinsics)`."""

    def __init__(
        self,
        database: PoseDatabase,
        config: LifterConfig = LifterConfig(),
        device: str | torch.device = "cpu",
        cache_indices: bool = True,
        prior: LiftingPrior | None = None,
    ):
        """prior: the database's learnt lifting prior, used where config.prior says so."""
        self.device = torch.device(device)
        self.prior = None if prior is None else prior.to(self.device)
        self.retriever = PoseRetriever(database, config.index, cache=cache_indices)
        # the candidates are gathered and rotated on the device, and searched there (place)
        self.database = dataclasses.replace(
            database,
            poses=database.poses.to(self.device),
            rotations=database.rotations.to(self.device),
        )
        self.configure(config)
        if self.device.type != "cpu" and config.retrieval_on_device:
            self.retriever.place(self.device)
        source = database.manifest.get("source", "posedb")
        self.database_id = f"{source}-{database_digest(database)}"

    @property
    def model_id(self) -> str:
        """What answers name as their model: the database and, where it is used, the prior."""
        if self.prior is None or not self.config.prior:
            return self.database_id
        return f"{self.database_id}+prior-{self.prior.digest}"

    def configure(self, config: LifterConfig) -> None:
        """Change the algorithm parameters (not the index) of a loaded lifter."""
        if config.index != self.retriever.config:
            raise ValueError("the index settings are fixed when a Lifter is built")
        self.config = config
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
        models/posedb-cmu holds the CMU one), and its learnt prior where its folder holds one
        (`prior/`, ds3d.mocap.prior)."""
        directory = require_models((Path(model_dir) if model_dir else MODELS_DIR) / database)
        db, learnt = PoseDatabase.load(directory), directory / PRIOR_DIR
        prior = LiftingPrior.load(learnt) if learnt.is_dir() else None
        if prior is not None and prior.manifest["database"]["digest"] != database_digest(db):
            raise DataFormatError(
                f"{learnt} was trained on another database than {directory}'s: train it again "
                "(ds3d train-prior) or remove it"
            )
        return cls(db, config, device, prior=prior)

    @torch.inference_mode()  # no autograd anywhere: a third less overhead per op at batch 1
    def lift(self, joints_2d, visible=None, intrinsics=None, camera=None) -> LiftResult:
        """joints_2d: (B, 14, 2) px, LSP order; visible: optional (B, 14) bool; intrinsics:
        optional (B, 3, 3) (without: weak perspective); camera: optional (B, 3, 3), without
        intrinsics the camera in whose coordinates to place the people (root_position), e.g.
        an assumed one (ds3d.fit.camera.pinhole). Raises ds3d.errors.InvalidPose.
        Every stage runs on the (pose, set) problems that config.partial_sets scores, each
        stage once for all of them."""
        query = self.query(joints_2d, visible, intrinsics)
        placed_by = query.frame.intrinsics
        if (
            placed_by is None
            and (given := intrinsics_batch(camera, len(query.joints_2d))) is not None
        ):
            placed_by = given.to(self.device)
        return self._lift(query, placed_by)

    @torch.inference_mode()
    def run(self, inputs: Sequence[PoseInput]) -> LiftResult:
        """lift() of B 2D poses already checked (ds3d.inputs.pose_input), each with its own
        intrinsics or none (those without are not placed: NaN rows of root_position)."""
        parts = []
        for rows in group_rows(item.intrinsics is not None for item in inputs).values():

            def stacked(name: str, rows=rows) -> torch.Tensor:
                values = np.stack([getattr(inputs[i], name) for i in rows])
                return torch.from_numpy(values).to(self.device)

            x, visible = stacked("joints_2d"), stacked("visible")
            k = None if inputs[rows[0]].intrinsics is None else stacked("intrinsics")
            parts.append((rows, self._lift(Query.of(x, visible, k), k)))
        return LiftResult.gather(parts)

    def _lift(self, query: Query, placed_by: torch.Tensor | None) -> LiftResult:
        """The stages of lift() on a query, its people placed by the camera `placed_by`
        (B, 3, 3) where given."""
        timings: dict[str, float]
        problems, timings = self.problems(query), {}
        found = self.neighbours(problems, timings=timings)
        with stage_timer(timings, "selection", self.device):
            kept, weights, kept_residuals = self.weight_neighbours(found.poses, -found.residuals)
            energy = self.set_energies(kept, weights, kept_residuals, found.params, problems)
            chosen, energies = self.choose(problems, energy)
        with stage_timer(timings, "pose_fit", self.device):
            pose, projection, root = self.fit_pose(
                kept[chosen], weights[chosen], found.params[chosen], problems.take(chosen)
            )
        return LiftResult(
            joints_3d=pose.cpu(),
            bone_lengths=bone_lengths(pose).cpu(),
            joint_set=self.set_names(problems.joint_set[chosen]),
            energy=energy[chosen].cpu(),
            set_energies=energies.cpu(),
            projection=projection.cpu(),
            root_position=None
            if placed_by is None
            else self.root_position(root, projection, query.frame, placed_by).cpu(),
            timings_ms=timings,
        )

    def query(self, joints_2d, visible=None, intrinsics=None) -> Query:
        """Checked 2D input on the lifter's device, with its camera frame. Arguments as lift;
        raises ds3d.errors.InvalidPose."""
        x = joints_2d_batch(joints_2d).to(self.device)
        vis = visibility_batch(visible, len(x)).to(self.device)
        k = intrinsics_batch(intrinsics, len(x))
        return Query.of(x, vis, None if k is None else k.to(self.device))

    def problems(self, query: Query, sets: str | torch.Tensor = "scored") -> Problems:
        """The problems of query's B poses. sets: "scored", those `lift` scores
        (config.partial_sets); "every", every configured set of every pose, pose-major (P =
        B x S: `.unflatten(0, (B, S))` gives per-pose tables); or (B,) long, one set per pose."""
        b, n_sets = len(query.joints_2d), len(self.set_ids)
        if isinstance(sets, torch.Tensor):
            pose, joint_set = torch.arange(b, device=sets.device), sets
        elif sets == "every":
            pose = torch.arange(b).repeat_interleave(n_sets)
            joint_set = torch.arange(n_sets).repeat(b)
        elif sets == "scored":
            pose, joint_set = self._scored_sets(query.visible).nonzero().unbind(1)
        else:
            raise ValueError(f"sets must be 'scored', 'every' or a tensor, got {sets!r}")
        pose, joint_set = pose.to(self.device), joint_set.to(self.device)
        own = query.take(pose)
        masks = self.set_masks[joint_set] * own.visible.float()
        return Problems(query, pose, joint_set, own, masks)

    def set_names(self, joint_set: torch.Tensor) -> list[str]:
        """Indices into config.joint_sets -> their names."""
        return [self.config.joint_sets[i] for i in joint_set.tolist()]

    def _scored_sets(self, visible: torch.Tensor) -> torch.Tensor:
        """(B, S) bool on the CPU: the sets `lift` scores for each pose (config.partial_sets)."""
        usable = self._usable_sets(visible).cpu()
        if self.config.partial_sets == "always":
            return torch.ones_like(usable)
        if "all" in self.config.joint_sets:  # every joint visible: `all` alone
            only_all = torch.tensor([name == "all" for name in self.config.joint_sets])
            usable[visible.all(-1).cpu()] = only_all
        return usable

    def _usable_sets(self, visible: torch.Tensor) -> torch.Tensor:
        """(B, S) bool: a set with a hidden joint only counts when every set has one."""
        masks = self.set_masks * visible[:, None].float()
        complete = (masks == self.set_masks).all(-1)
        return complete | ~complete.any(-1, keepdim=True)

    @torch.inference_mode()
    def neighbours(
        self,
        problems: Problems,
        start: torch.Tensor | None = None,
        timings: dict[str, float] | None = None,
    ) -> Neighbours:
        """Retrieval and projection fit (eq:projerr1): K neighbours per problem and the
        projection M_s fitted to them. start: optional (P, 6) projections to start the fit from
        (a previous iteration's). Adds the stages' ms to `timings`."""
        timings = {} if timings is None else timings
        with stage_timer(timings, "retrieval", self.device):
            poses = self.retrieve(problems)
        with stage_timer(timings, "projection_fit", self.device):
            params, residuals = self.fit_projections(poses, problems, start)
        return Neighbours(poses, params, residuals)

    def retrieve(self, problems: Problems) -> torch.Tensor:
        """K neighbours of each problem from its set's index. Returns (P, K, 14, 3) mm,
        camera-oriented."""
        joints_2d = problems.own.joints_2d
        shape = (len(joints_2d), self.config.neighbours)
        ids = torch.empty(shape, dtype=torch.long, device=joints_2d.device)
        for s in problems.joint_set.unique().tolist():
            take = (problems.joint_set == s).nonzero()[:, 0].to(joints_2d.device)
            found = self.retriever.search(
                joints_2d[take],
                self.config.neighbours,
                self.config.nprobe,
                (self.config.joint_sets[s],),
                self.config.retrieval_on_device,
            )
            ids[take] = found[:, 0]
        return self.database.candidates(ids.to(self.device))

    def fit_projections(self, candidates, problems: Problems, start=None):
        """eq:projerr1 for every problem, all in one solve on all 14 joints with the set's own
        masked, on the `projection_neighbours` nearest of the K candidates (P, K, 14, 3);
        start: optional (P, 6). Returns params (P, 6) and the residuals of all K (P, K)."""
        params = fit_projection(
            candidates[:, : self.config.projection_neighbours],
            problems.own.joints_2d,
            problems.masks,
            problems.own.frame,
            start,
            self.config.projection_iterations,
        )
        projected = project(candidates, params, problems.own.frame)
        return params, projection_energy(projected, problems.own.joints_2d, problems.masks)

    def weight_neighbours(self, candidates, scores):
        """eq:wt/eq:wtn. candidates: (..., K, 14, 3); scores: (..., K), higher is better.
        Returns the kept neighbours (..., K_w, 14, 3), weights (..., K_w) and their -scores."""
        if not self.config.weighting:
            return candidates, torch.ones_like(scores), -scores
        index, weights = top_weighted(scores, self.config.weighted_neighbours)
        kept = torch.take_along_dim(candidates, index[..., None, None], dim=-3)
        return kept, weights, -torch.take_along_dim(scores, index, dim=-1)

    def set_energies(self, kept, weights, kept_residuals, params, problems: Problems):
        """eq:energyS of each problem: kept (P, K_w, 14, 3), best weighted first (without
        weighting: nearest first); weights, kept_residuals (P, K_w); params (P, 6). Scored on
        the first config.selection_neighbours. Returns (P,)."""
        n = self.config.selection_neighbours
        kept, weights, kept_residuals = kept[:, :n], weights[:, :n], kept_residuals[:, :n]
        if self.config.select_on_all_joints:
            kept_residuals = projection_energy(
                project(kept, params, problems.own.frame),
                problems.own.joints_2d,
                problems.own.visible.float(),
            )
        return set_energy(kept, weights, kept_residuals, self.config.omega)

    def choose(self, problems: Problems, cost: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """s^: per pose, its problem of least cost (P,) among the usable sets (a set with a
        hidden joint only counts when every set has one; ties: the first set). Returns the
        chosen problem of each of the B poses (B,) long, and the costs as a (B, S) table, inf
        where a set was not among the problems."""
        b, dev = len(problems.query.joints_2d), cost.device
        table = torch.full((b, len(self.set_ids)), torch.inf, device=dev, dtype=cost.dtype)
        table[problems.pose, problems.joint_set] = cost
        usable = self._usable_sets(problems.query.visible)
        best = torch.where(usable, table, torch.inf).argmin(-1)
        problem_of = torch.zeros(b, len(self.set_ids), dtype=torch.long, device=dev)
        problem_of[problems.pose, problems.joint_set] = torch.arange(len(cost), device=dev)
        return problem_of[torch.arange(b, device=dev), best], table

    def learnt_poses(self, problems: Problems, params: torch.Tensor) -> torch.Tensor | None:
        """The learnt prior's pose of each problem's person from all its visible joints, in the
        orientation of its neighbours (turned by the inverse of its projection's rotation,
        params (P, 6)): (P, 14, 3) mm; None without a prior or with config.prior off."""
        if self.prior is None or not self.config.prior:
            return None
        own = problems.own
        in_camera = self.prior(own.joints_2d, own.visible, own.frame.intrinsics)
        # camera = R neighbours' frame, row by row: x_neighbours = x_camera R
        return in_camera @ rotation_matrix(params[:, :3])

    def fit_pose(self, kept, weights, params, problems: Problems):
        """eq:energyMin2 of one problem per pose (its chosen set): kept (B, K_w, 14, 3), weights
        (B, K_w), params (B, 6); with the learnt prior's pose (learnt_poses) where there is one.
        Returns the pose (B, 14, 3) mm, camera-oriented, root at the
        hip midpoint, with the person's proportions, its projection (B, 6), and where its hip
        midpoint lies from the origin that the projection places (B, 3) mm (root_position)."""
        pose, projection = fit_pose(
            kept,
            weights,
            params,
            problems.own.joints_2d,
            problems.masks,
            problems.own.frame,
            self.config.omega,
            self.config.pca_components,
            self.config.pose_iterations,
            self.config.proportions,
            self.learnt_poses(problems, params),
        )
        oriented = pose @ rotation_matrix(projection[:, :3]).transpose(-1, -2)
        root = hip_midpoint(oriented)
        return oriented - root[:, None], projection, root

    @staticmethod
    def root_position(
        root: torch.Tensor, projection: torch.Tensor, frame: CameraFrame, camera: torch.Tensor
    ) -> torch.Tensor:
        """The hip midpoint in the coordinates of `camera` (B, 3, 3), mm (B, 3): fit_pose's root
        (B, 3) moved by its projection (B, 6) fitted in `frame`."""
        return root + camera_translation(projection[:, 3:], frame, camera)
