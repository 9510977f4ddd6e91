"""Nearest-neighbour retrieval of 3D poses from a 2D query: one faiss index per joint set.

Each index holds, for every database entry (pose x virtual view), the normalised 2D pose of the
set's joints; a query is normalised the same way, so retrieval ignores the camera and the scale.
Faiss ranks by squared L2 over the set's joints (the paper uses the mean joint distance: the same
neighbours up to ties, and faiss's exact and IVF indices support it).

Off the CPU, the lists of the indices are copied to the device and searched there in torch
(DeviceLists: the same lists visited and the same vectors, so the same neighbours up to ties), so
that a batch's 2D poses need not come back to the CPU; on the CPU faiss stays, far faster there
(256 queries of one set: about 40-60 ms against 1.6-2.8 s).

Indices are rebuilt from the pose database (a few MB) rather than shipped (hundreds of MB), and
cached on disk under $DS3D_CACHE_DIR (default ~/.cache/ds3d) keyed by the database content and
the index settings, so a process loads them in seconds after the first build.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import faiss
import numpy as np
import torch

from ds3d.mocap.database import PoseDatabase
from ds3d.mocap.normalize import normalize_2d
from ds3d.skeleton import JOINT_SETS, SET_NAMES
from ds3d.util.progress import progress


@dataclass(frozen=True)
class IndexConfig:
    """How an index is built. kind: "flat" (exact) or "ivf" (inverted file with `nlist` lists,
    approximate; how many lists a search visits is a search-time setting, `nprobe`). storage:
    "f32", "f16" (half floats) or "sq8" (8 bits per dimension over its trained range: a
    quarter of f32's vector bytes). sq8 by default: the indices are nearly all of a served
    model's memory, and sq8 finds neighbours as good (docs/RESULTS.md, retrieval)."""

    kind: str = "ivf"
    nlist: int = 1024
    storage: str = "sq8"

    def factory_string(self) -> str:
        store = {"f32": "Flat", "f16": "SQfp16", "sq8": "SQ8"}[self.storage]
        if self.kind == "flat":
            return store
        if self.kind == "ivf":
            return f"IVF{self.nlist},{store}"
        raise ValueError(f"unknown index kind {self.kind!r} (flat or ivf)")


def cache_dir() -> Path:
    return Path(os.environ.get("DS3D_CACHE_DIR", Path.home() / ".cache" / "ds3d"))


def database_digest(db: PoseDatabase) -> str:
    digest = hashlib.sha1(db.poses.numpy().tobytes())
    digest.update(db.rotations.numpy().tobytes())
    return digest.hexdigest()[:16]


# faiss compares scalar-quantised codes 8 dimensions at a time (SIMD) only where the dimension is a
# multiple of 8, else one at a time (unpadded, float16 retrieval was 1.7x float32's; padded, it
# is faster: docs/RESULTS.md, retrieval). The vectors are padded with zeros to such a
# dimension, which changes no distance.
SIMD_DIMS = 8


def index_dim(joint_set: str) -> int:
    """The dimension of `joint_set`'s index: its 2D coordinates, padded to SIMD_DIMS."""
    return -(-2 * len(JOINT_SETS[joint_set]) // SIMD_DIMS) * SIMD_DIMS


def padded(vectors: np.ndarray, dim: int) -> np.ndarray:
    """(N, d) float32 -> (N, dim) float32, zeros after the d given columns."""
    out = np.zeros((len(vectors), dim), np.float32)
    out[:, : vectors.shape[1]] = vectors
    return out


def build_index(db: PoseDatabase, joint_set: str, config: IndexConfig, seed: int = 0):
    """A faiss index over db's normalised 2D vectors of `joint_set` (zero-padded to
    index_dim), ids = entry ids."""
    dim = index_dim(joint_set)
    index = faiss.index_factory(dim, config.factory_string())
    if not index.is_trained:
        # Train the coarse quantiser on a fixed subsample: 64 points per list is what faiss's
        # k-means needs, and the seed makes the index reproducible.
        sample_poses = min(len(db.poses), max(1, 64 * config.nlist // db.num_views + 1))
        rng = np.random.default_rng(seed)
        subset = PoseDatabase(
            db.poses[np.sort(rng.choice(len(db.poses), sample_poses, False))], db.rotations
        )
        index.train(padded(np.concatenate(list(subset.projected_2d(joint_set))), dim))
    for block in db.projected_2d(joint_set):
        index.add(padded(block, dim))
    return index


# Candidate coordinates gathered at once by DeviceLists.search (float32): about 1 GB.
GATHER_ELEMENTS = 2**28


@dataclass
class DeviceLists:
    """A faiss index's inverted lists as tensors on one device, searched there in torch: the
    lists an IVF search visits, their vectors as faiss decodes them, ranked by squared L2, so
    the neighbours faiss finds up to ties, without a round trip to the CPU. An exact (flat)
    index is one list.

    centroids (L, d); vectors (N, d) float32 and ids (N,) int64 entry ids, list by list;
    starts, sizes (L,) int64: each list's first row and length."""

    centroids: torch.Tensor
    vectors: torch.Tensor
    ids: torch.Tensor
    starts: torch.Tensor
    sizes: torch.Tensor

    @classmethod
    def of(cls, index, device: torch.device | str) -> DeviceLists:
        """The lists of a faiss IVF or flat index, on `device`."""
        try:
            ivf = faiss.extract_index_ivf(index)
        except RuntimeError:  # flat: one list of every vector
            ids = np.arange(index.ntotal)
            centroids = np.zeros((1, index.d), np.float32)
            vectors, sizes = index.reconstruct_n(0, index.ntotal), np.array([index.ntotal])
        else:
            lists = ivf.invlists
            assert lists is not None, "an IVF index has its lists"
            sizes = np.array([lists.list_size(k) for k in range(ivf.nlist)])
            ids = np.concatenate(
                [
                    faiss.rev_swig_ptr(lists.get_ids(k), int(n)).copy()
                    for k, n in enumerate(sizes)
                    if n
                ]
            )
            ivf.make_direct_map()
            centroids = ivf.quantizer.reconstruct_n(0, ivf.nlist)
            vectors = index.reconstruct_batch(ids)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        arrays = (centroids, vectors, ids.astype(np.int64), starts, sizes.astype(np.int64))
        return cls(*(torch.from_numpy(np.ascontiguousarray(a)).to(device) for a in arrays))

    def search(self, queries: torch.Tensor, k: int, nprobe: int) -> torch.Tensor:
        """queries (B, d) on the lists' device -> (B, k) int64 entry ids, nearest first, -1
        where the visited lists hold fewer than k; as faiss's search with `nprobe`."""
        probes = (
            torch.cdist(queries, self.centroids)
            .topk(min(nprobe, len(self.centroids)), largest=False)
            .indices
        )  # (B, P), nearest list first
        lengths = self.sizes[probes]
        ends = lengths.cumsum(1)  # (B, P): each visited list's end among the query's candidates
        width = max(int(ends[:, -1].max()), 1)
        step = max(1, GATHER_ELEMENTS // (width * queries.shape[1]))
        found = [
            self._nearest(queries[i : i + step], probes[i : i + step], ends[i : i + step], width, k)
            for i in range(0, len(queries), step)
        ]
        return torch.cat(found)

    def _nearest(self, queries, probes, ends, width: int, k: int) -> torch.Tensor:
        """search() of some queries, their visited lists laid end to end in `width` slots."""
        slot = torch.arange(width, device=queries.device).repeat(len(queries), 1)
        probe = torch.searchsorted(ends, slot, right=True).clamp(max=probes.shape[1] - 1)
        first = ends.gather(1, probe) - self.sizes[probes].gather(1, probe)  # slots before it
        row = self.starts[probes].gather(1, probe) + slot - first
        valid = slot < ends[:, -1:]
        row = torch.where(valid, row, 0)
        distance = (self.vectors[row] - queries[:, None]).square().sum(-1)
        distance = torch.where(valid, distance, torch.inf)
        best = distance.topk(min(k, width), largest=False)
        ids = torch.where(best.values.isinf(), -1, self.ids[row.gather(1, best.indices)])
        return torch.nn.functional.pad(ids, (0, k - ids.shape[1]), value=-1)


class PoseRetriever:
    """The five per-set indices of one database.

    search(joints_2d (B, 14, 2), k, nprobe, sets) -> ids (B, S, k) int64 entry ids.
    """

    def __init__(self, db: PoseDatabase, config: IndexConfig = IndexConfig(), cache: bool = True):
        self.db = db
        self.config = config
        sets = progress(SET_NAMES, desc="pose indices", unit="set")
        self.indices = [self._load_or_build(name, cache) for name in sets]
        self.on_device: list[DeviceLists] | None = None  # place()

    def place(self, device: torch.device | str) -> None:
        """Copies of the indices' lists on `device` (DeviceLists), which search() then searches
        for queries on that device rather than faiss on the CPU."""
        self.on_device = [DeviceLists.of(index, device) for index in self.indices]

    def _load_or_build(self, joint_set: str, cache: bool):
        settings = "-".join(f"{k}{v}" for k, v in asdict(self.config).items())
        dim = index_dim(joint_set)
        path = cache_dir() / f"{database_digest(self.db)}-{settings}-{joint_set}-d{dim}.faiss"
        if cache and path.is_file():
            return faiss.read_index(str(path))
        index = build_index(self.db, joint_set, self.config)
        if cache:
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_suffix(f".{os.getpid()}.tmp")
            faiss.write_index(index, str(partial))
            partial.replace(path)  # atomic: concurrent replicas never read half a file
        return index

    def search(
        self,
        joints_2d: torch.Tensor,
        k: int,
        nprobe: int = 8,
        sets: tuple[str, ...] = SET_NAMES,
        on_device: bool = True,
    ) -> torch.Tensor:
        """joints_2d: (B, 14, 2) float, any unit; nprobe: inverted lists an IVF index visits;
        sets: the joint sets to search; on_device: where the lists were placed on the queries'
        device, search them there (else faiss on the CPU). Returns (B, len(sets), k) int64
        entry ids on the queries' device (-1 where an approximate index found fewer than k)."""
        lists = self.on_device
        if not on_device or lists is None or lists[0].vectors.device != joints_2d.device:
            lists = None
        ids = []
        for name in sets:
            s = SET_NAMES.index(name)
            query = normalize_2d(joints_2d[:, list(JOINT_SETS[name])].float())
            query = query.reshape(len(query), -1)
            index = self.indices[s]
            if lists is not None:
                query = torch.nn.functional.pad(query, (0, index.d - query.shape[1]))
                ids.append(lists[s].search(query, k, nprobe))
                continue
            if hasattr(index, "nprobe"):
                index.nprobe = nprobe
            _, found = index.search(padded(query.cpu().numpy(), index.d), k)
            ids.append(torch.from_numpy(found).to(joints_2d.device))
        return torch.stack(ids, dim=1)
