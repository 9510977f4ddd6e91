import math

import numpy as np
import pytest
import torch

from ds3d.data.h36m import load_h36m_sequences
from ds3d.errors import DataFormatError
from ds3d.mocap.database import PoseDatabase, deduplicate
from ds3d.mocap.normalize import normalize_2d, normalize_3d
from ds3d.mocap.retrieval import IndexConfig, PoseRetriever
from ds3d.mocap.views import view_rotations
from ds3d.skeleton import HEAD_TOP, L_HIP, R_ANKLE, R_HIP


@pytest.fixture(scope="module")
def walking(data_dir):
    return torch.from_numpy(load_h36m_sequences(("S9",))["S9/Walking 1"][::25])


def yaw(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # about z (up)


def test_normalisation_is_invariant_to_translation_and_yaw(walking):
    moved = walking @ yaw(1.1).T + torch.tensor([1500.0, -700.0, 20.0])
    torch.testing.assert_close(normalize_3d(moved), normalize_3d(walking), atol=1e-2, rtol=0)


def test_normalised_pose_is_rooted_upright_and_faces_the_camera(walking):
    body = normalize_3d(walking)
    root = (body[:, R_HIP] + body[:, L_HIP]) / 2
    torch.testing.assert_close(root, torch.zeros(len(body), 3), atol=1e-3, rtol=0)
    assert bool((body[:, HEAD_TOP, 1] < body[:, R_ANKLE, 1]).all())  # y down
    assert bool((body[:, L_HIP, 0] > 0).all())  # the person's left is +x: facing -z


def test_normalised_2d_spans_minus_one_to_one_in_y():
    points = torch.rand(5, 14, 2) * 300 + 40
    out = normalize_2d(points)
    torch.testing.assert_close(out[..., 1].amin(-1), -torch.ones(5))
    torch.testing.assert_close(out[..., 1].amax(-1), torch.ones(5))
    torch.testing.assert_close(normalize_2d(points * 3 + 17), out, atol=1e-5, rtol=0)


def test_virtual_views_are_the_papers_144_rotations():
    rotations = view_rotations()
    assert rotations.shape == (144, 3, 3)
    identity = torch.eye(3).expand(144, 3, 3)
    torch.testing.assert_close(rotations @ rotations.transpose(-1, -2), identity)
    # Positive elevation lifts the camera: the head (up, -y) comes nearer (smaller z).
    head = torch.tensor([0.0, -1000.0, 0.0])
    elevated = rotations[5 * 24]  # elevation 75, azimuth 0
    assert float((elevated @ head)[2]) < 0


def test_deduplicate_drops_near_copies_only():
    base = torch.randn(50, 14, 3).numpy() * 200
    noisy = base + np.random.default_rng(0).normal(0, 1.0, base.shape)
    kept = deduplicate(np.concatenate([base, noisy]).astype(np.float32), threshold_mm=10)
    np.testing.assert_array_equal(kept, np.arange(50))


def test_flat_retrieval_returns_the_true_nearest_neighbours(walking):
    db = PoseDatabase.from_world_poses(walking.numpy(), dedupe_mm=1.0)
    retriever = PoseRetriever(db, IndexConfig(kind="flat", storage="f32"), cache=False)
    query = db.candidates(torch.tensor([7 * 144 + 30, 3 * 144 + 100]))[..., :2] * 0.3 + 250
    found = retriever.search(query, k=10)  # (2, 5, 10)
    for s, vectors in enumerate(db.projected_2d(name) for name in ("all", "up", "lw", "lt", "rt")):
        from ds3d.skeleton import JOINT_SETS, SET_NAMES

        table = torch.from_numpy(np.concatenate(list(vectors)))
        q = normalize_2d(query[:, list(JOINT_SETS[SET_NAMES[s]])]).flatten(1)
        brute = torch.cdist(q, table).topk(10, largest=False).indices
        np.testing.assert_array_equal(found[:, s].numpy(), brute.numpy())
    assert found[0, 0, 0] == 7 * 144 + 30  # the entry itself comes first


def test_database_round_trip_and_bad_files(tmp_path, walking):
    db = PoseDatabase.from_world_poses(walking.numpy(), dedupe_mm=1.0, manifest={"source": "t"})
    db.save(tmp_path / "db")
    again = PoseDatabase.load(tmp_path / "db")
    torch.testing.assert_close(again.poses, db.poses)
    assert again.manifest["source"] == "t"
    (tmp_path / "bad").mkdir()
    np.save(tmp_path / "bad" / "poses.npy", np.zeros((3, 17, 3)))
    (tmp_path / "bad" / "manifest.json").write_text("{}")
    with pytest.raises(DataFormatError, match="expected"):
        PoseDatabase.load(tmp_path / "bad")
    with pytest.raises(DataFormatError):
        PoseDatabase.load(tmp_path / "missing")


def test_candidates_are_database_poses_turned_by_their_view(walking):
    db = PoseDatabase.from_world_poses(walking.numpy(), dedupe_mm=1.0)
    entry = 2 * 144 + 37
    expected = db.poses[2] @ db.rotations[37].T
    torch.testing.assert_close(db.candidates(torch.tensor([entry]))[0], expected)


@pytest.mark.parametrize(
    "config", [IndexConfig(kind="ivf", nlist=16, storage="sq8"), IndexConfig("flat", 1, "f32")]
)
def test_the_lists_searched_in_torch_give_faiss_neighbours(walking, config):
    """PoseRetriever.place: the indices' lists searched in torch on a device (here the CPU, as
    a GPU machine's lifter does on CUDA) find the neighbours faiss finds (up to ties)."""
    db = PoseDatabase.from_world_poses(walking.numpy(), dedupe_mm=1.0)
    retriever = PoseRetriever(db, config, cache=False)
    entries = torch.arange(0, len(db.poses) * db.num_views, 331)[:24]
    query = db.candidates(entries)[..., :2] * 0.3 + 250 + torch.randn(len(entries), 14, 2)
    by_faiss = retriever.search(query, k=32, nprobe=4)
    retriever.place("cpu")
    in_torch = retriever.search(query, k=32, nprobe=4)
    assert in_torch.shape == by_faiss.shape == (len(entries), 5, 32)
    shared = [
        len(set(a.tolist()) & set(b.tolist()))
        for a, b in zip(in_torch.flatten(0, 1), by_faiss.flatten(0, 1), strict=True)
    ]
    assert np.mean(shared) / 32 > 0.99
    # faiss on the CPU still, when asked
    torch.testing.assert_close(retriever.search(query, 32, 4, on_device=False), by_faiss)
