import dataclasses

import torch

from ds3d.cli import main as cli
from ds3d.errors import DataFormatError
from ds3d.fit.bones import GROUP_LOG_SD, bone_lengths, group_spread
from ds3d.lifter import Lifter
from ds3d.mocap.database import PoseDatabase
from ds3d.mocap.normalize import normalize_2d
from ds3d.mocap.prior import NETWORKS, PriorShape
from ds3d.mocap.retrieval import database_digest
from ds3d.skeleton import NUM_JOINTS, hip_midpoint
from ds3d.training.prior import (
    PriorTraining,
    draw,
    noise_error,
    train_network,
    train_prior,
)
from ds3d.util.paths import MODELS_DIR

# Seconds, not minutes: small networks, a few hundred steps of small batches.
TINY = PriorTraining(
    steps=300,
    noise_steps=300,
    batch=64,
    lr=3e-3,
    shape=PriorShape(width=64, blocks=1),
    noise_shape=PriorShape(width=32, blocks=1, dropout=0.0, outputs=1),
    validation=512,
)


def bundled(n: int) -> PoseDatabase:
    """The first n poses of the bundled database."""
    db = PoseDatabase.load(MODELS_DIR / "posedb")
    return dataclasses.replace(db, poses=db.poses[:n])


def test_a_distant_pair_is_the_pose_seen_from_its_camera():
    """Without noise, hidden joints or other proportions, and from so far that the view is
    orthographic, a pair's 2D is its target's x and y normalised, and the target is the
    database's pose, turned (its bones as long, left and right possibly swapped by the mirror)
    and rooted at the hip midpoint."""
    db = bundled(1)
    cfg = dataclasses.replace(TINY, bone_sd=0.0, hidden=0.0, noise_sd=0.0, distance_mm=(1e8, 1e8))
    pairs = draw(db.poses, cfg, torch.Generator().manual_seed(0))
    coordinates = pairs.features[:, : 2 * NUM_JOINTS].unflatten(1, (NUM_JOINTS, 2))
    expected = normalize_2d(pairs.target[..., :2])
    torch.testing.assert_close(coordinates, expected, atol=1e-4, rtol=0)
    assert bool((pairs.features[:, 2 * NUM_JOINTS :] == 1).all())
    assert bool((pairs.sigma == 0).all())
    lengths = bone_lengths(pairs.target).sort(-1).values
    expected = bone_lengths(db.poses[0]).sort(-1).values.expand_as(lengths)
    torch.testing.assert_close(lengths, expected, atol=1e-2, rtol=0)
    torch.testing.assert_close(hip_midpoint(pairs.target), torch.zeros(cfg.batch, 3))


def test_the_bone_groups_spread_as_people_differ_at_the_rms_asked():
    """The groups that differ more between people (a head, a pelvis) are drawn wider than those
    that differ less (a forearm), in the same proportions, at the RMS asked."""
    spread = group_spread(0.16)
    torch.testing.assert_close(spread.pow(2).mean().sqrt(), torch.tensor(0.16))
    torch.testing.assert_close(spread / spread.max(), GROUP_LOG_SD / GROUP_LOG_SD.max())


def test_hidden_joints_are_flagged_and_zeroed():
    cfg = dataclasses.replace(TINY, hidden=1.0, batch=256)
    pairs = draw(bundled(50).poses, cfg, torch.Generator().manual_seed(1))
    flags = pairs.features[:, 2 * NUM_JOINTS :]
    hidden = (flags == 0).sum(-1)
    assert bool(((hidden >= 1) & (hidden <= 4)).all()), hidden
    coordinates = pairs.features[:, : 2 * NUM_JOINTS].unflatten(1, (NUM_JOINTS, 2))
    assert bool((coordinates[flags == 0] == 0).all())


def test_the_noise_is_a_share_of_clean_poses_and_sigmas_up_to_noise_sd():
    cfg = dataclasses.replace(TINY, batch=4096)
    sigma = draw(bundled(50).poses, cfg, torch.Generator().manual_seed(2)).sigma
    clean = float((sigma == 0).float().mean())
    assert abs(clean - cfg.clean) < 0.05, clean  # 4,096 draws: the share's sd is 0.007
    assert float(sigma.max()) <= cfg.noise_sd
    assert float(sigma[sigma > 0].mean()) > 0.4 * cfg.noise_sd  # uniform: half of it


def test_a_short_training_learns_and_is_reproducible():
    """A few hundred steps on 500 poses: the held-out pairs' error falls well below that of
    the database's mean pose (what a lifting network that learnt nothing of the 2D would answer),
    and the same seed gives the same networks."""
    db = bundled(500)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the same sums in the same order in both runs
    try:
        prior = train_prior(db, TINY)
        again = train_prior(db, TINY)
    finally:
        torch.set_num_threads(threads)
    for name in NETWORKS:
        state = again.nets[name].state_dict()
        for key, value in prior.nets[name].state_dict().items():
            assert torch.equal(value, state[key]), (name, key)
    held = draw(db.poses, dataclasses.replace(TINY, batch=512), torch.Generator().manual_seed(1))
    mean_pose = float((held.target - held.target.mean(0)).norm(dim=-1).mean())
    metrics = prior.manifest["metrics"]
    assert metrics["clean"]["validation"] < 0.75 * mean_pose
    assert metrics["noisy"]["validation"] < 0.75 * mean_pose
    assert prior.manifest["seed"] == TINY.seed
    assert prior.manifest["database"]["digest"] == database_digest(db)


def test_the_noise_estimator_learns_the_noise_level():
    """On noise large enough for a tiny estimator to learn in 300 steps, its held-out error
    falls well below that of the best constant (the sigmas' median)."""
    db = bundled(500)
    cfg = dataclasses.replace(TINY, noise_sd=0.5)
    held = draw(db.poses, dataclasses.replace(cfg, batch=512), torch.Generator().manual_seed(1))
    constant = float((held.sigma - held.sigma.median()).abs().mean())
    _, metrics = train_network(db, cfg, TINY.noise_shape, 300, noise_error, seed=5)
    assert metrics["validation"] < 0.75 * constant  # 0.51 measured


def test_train_prior_writes_the_prior_the_lifter_loads(tmp_path):
    """Into the database's folder, where Lifter.load finds it (the bundled database, whose
    indices are cached); a prior of another database is refused."""
    (tmp_path / "posedb").mkdir()
    for name in ("poses.npy", "manifest.json"):
        (tmp_path / "posedb" / name).symlink_to(MODELS_DIR / "posedb" / name)
    args = ["train-prior", "--model-dir", str(tmp_path), "--set", "steps=20"]
    args += ["--set", "noise_steps=20", "--set", "batch=32", "--set", "validation=64"]
    args += ["--set", "shape.width=16"]
    assert cli(args) == 0
    saved = {p.name for p in (tmp_path / "posedb" / "prior").iterdir()}
    assert saved == {"prior.pt", "manifest.json"}
    lifter = Lifter.load(tmp_path)
    assert lifter.prior is not None
    manifest = lifter.prior.manifest
    assert manifest["training"]["steps"] == 20 and manifest["training"]["shape"]["width"] == 16
    assert manifest["database"]["digest"] == database_digest(
        PoseDatabase.load(MODELS_DIR / "posedb")
    )
    (tmp_path / "posedb-cmu").mkdir()
    for name in ("poses.npy", "manifest.json"):
        (tmp_path / "posedb-cmu" / name).symlink_to(MODELS_DIR / "posedb-cmu" / name)
    (tmp_path / "posedb" / "prior").rename(tmp_path / "posedb-cmu" / "prior")
    try:
        Lifter.load(tmp_path, database="posedb-cmu")
    except DataFormatError as err:
        assert "another database" in str(err)
    else:
        raise AssertionError("a prior of another database was loaded")
