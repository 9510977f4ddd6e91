import numpy as np
import torch

from ds3d.evaluation.metrics import align, mpjpe, pa_mpjpe, pck, rigid_error, torso_diameter
from ds3d.fit.camera import rotation_matrix


def random_poses(n=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 14, 3, generator=g, dtype=torch.float64) * 300


def test_rigid_alignment_recovers_a_known_rotation_and_translation():
    gt = random_poses()
    rotation = rotation_matrix(torch.tensor([[0.3, -1.2, 2.0]], dtype=torch.float64))
    moved = gt @ rotation.transpose(-1, -2) + torch.tensor([100.0, -50.0, 3000.0])
    assert mpjpe(moved, gt).min() > 100
    np.testing.assert_allclose(align(moved, gt, scale=False), gt, atol=1e-6)
    assert rigid_error(moved, gt).max() < 1e-6


def test_rigid_error_does_not_forgive_scale_but_pa_mpjpe_does():
    gt = random_poses()
    assert rigid_error(gt * 1.2, gt).min() > 1
    assert pa_mpjpe(gt * 1.2, gt).max() < 1e-6


def test_alignment_never_mirrors():
    gt = random_poses()
    mirrored = gt * torch.tensor([-1.0, 1.0, 1.0])
    # A reflection would align a mirrored pose perfectly; a rotation cannot.
    assert rigid_error(mirrored, gt).min() > 10


def test_pck_counts_joints_within_a_fifth_of_the_torso():
    gt = torch.zeros(1, 14, 2, dtype=torch.float64)
    gt[0, 8] = torch.tensor([0.0, 0.0])  # R shoulder
    gt[0, 3] = torch.tensor([0.0, 100.0])  # L hip
    gt[0, 9] = torch.tensor([30.0, 0.0])  # L shoulder
    gt[0, 2] = torch.tensor([30.0, 100.0])  # R hip
    diameter = float(np.hypot(30, 100))
    pred = gt.clone()
    pred[0, 0, 0] += 0.19 * diameter
    pred[0, 1, 0] += 0.21 * diameter
    per_joint = pck(pred, gt)
    assert per_joint[0] == 1 and per_joint[1] == 0
    assert pck(pred, gt, visible=torch.tensor([[True] + [False] * 13]))[1] == 0


def test_the_torso_of_a_partly_annotated_person_is_its_placed_diagonals():
    """LSPet places only the joints it sees: a diagonal with an unplaced end (junk coordinates)
    leaves the torso to the other one; with neither, the torso is undefined."""
    gt = torch.zeros(3, 14, 2, dtype=torch.float64)
    gt[:, 8], gt[:, 3] = torch.tensor([0.0, 0.0]), torch.tensor([0.0, 100.0])  # R sh., L hip
    gt[:, 9], gt[:, 2] = torch.tensor([30.0, 0.0]), torch.tensor([30.0, 60.0])  # L sh., R hip
    placed = torch.ones(3, 14, dtype=torch.bool)
    placed[1, 2] = False  # the other diagonal's hip unplaced
    placed[2, [2, 8]] = False  # neither diagonal whole
    diameter = torso_diameter(gt, placed)
    np.testing.assert_allclose(diameter[:2], [(100 + 60) / 2, 100.0])
    assert diameter[2].isnan() and torso_diameter(gt)[2].isfinite()
    pred = gt.clone()
    pred[:, 0, 0] += 60  # 60 px off: within 0.2 x 400 px, not within 0.2 x 100 px
    per_joint = pck(pred, gt, reference=torch.tensor([400.0, 100.0, 100.0]))
    assert per_joint[0] == 1 / 3  # within 0.2 x 400 only
