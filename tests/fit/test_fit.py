import pytest
import torch

from ds3d.fit import gauss_newton
from ds3d.fit.bones import bone_lengths, bone_scales, bone_vectors, scaling_map
from ds3d.fit.camera import (
    CameraFrame,
    camera_translation,
    initial_params,
    project,
    rotation_matrix,
    rotation_vector,
)
from ds3d.fit.gauss_newton import Residuals
from ds3d.fit.selection import top_weighted
from ds3d.fit.solve import (
    LEARNT_BONE_BAND,
    EnergyWeights,
    PoseProblem,
    fit_projection,
    projection_problem,
    turn,
    weighted_pca,
    within_band,
)
from ds3d.skeleton import BONE_GROUPS, hip_midpoint


def test_gauss_newton_solves_each_robust_problem_independently():
    """Robust fourth-root distances to a few points: each problem's minimum is the point the
    others do not outvote (a weighted geometric median); the energy never rises."""
    g = torch.Generator().manual_seed(0)
    points = torch.randn(4, 5, 3, generator=g) * 10  # (P, T, 3)
    points[:, 1:] = points[:, :1] + torch.randn(4, 4, 3, generator=g) * 0.01  # 4 agree, 1 not
    points[:, 0] += 50

    def evaluate(x, with_jacobian):
        jacobian = torch.eye(3).expand(4, 1, 3, 3) if with_jacobian else None
        return [Residuals(torch.ones(4, 5), x[:, None] - points, jacobian)]

    start = points.mean(1)
    x, value = gauss_newton.minimize(evaluate, start, iterations=40)
    start_value = gauss_newton.total_energy(evaluate(start, False))
    assert bool((value < start_value).all())
    torch.testing.assert_close(x, points[:, 1:].mean(1), atol=0.05, rtol=0)


@pytest.mark.parametrize(
    ("perspective", "proportions", "learnt"),
    [(p, s, False) for p in (True, False) for s in (True, False)]
    + [(True, True, True), (False, False, True)],
)
def test_analytic_jacobians_equal_autograd(perspective, proportions, learnt):
    """The fits' hand-written Jacobians against autograd's, in float64, at a random point (with
    a learnt pose: its direction and E_l too)."""
    g = torch.Generator().manual_seed(1)
    d = torch.float64
    candidates = torch.randn(3, 5, 14, 3, generator=g, dtype=d) * 300
    joints_2d = torch.randn(3, 14, 2, generator=g, dtype=d) * 50 + 300
    mask = (torch.rand(3, 14, generator=g) > 0.2).to(d)
    k = torch.tensor([[1000.0, 0, 320], [0, 1100, 240], [0, 0, 1]], dtype=d).expand(3, 3, 3)
    frame = CameraFrame(
        k if perspective else None, joints_2d.mean(1), torch.full((3,), 80.0, dtype=d)
    )
    params = initial_params(candidates, joints_2d, mask, frame)
    params = params + torch.randn(3, 6, generator=g, dtype=d) * 0.1

    def compare(evaluate, point, moved):
        analytic = evaluate(point, True)
        for i, group in enumerate(analytic):
            full = torch.autograd.functional.jacobian(
                lambda u, i=i: evaluate(moved(u), False)[i].value,
                torch.zeros_like(point[:, : group.jacobian.shape[-1]]),
            )
            per_problem = torch.stack([full[p, :, :, p] for p in range(len(point))])
            torch.testing.assert_close(group.jacobian.expand_as(per_problem), per_problem)

    state = torch.cat([rotation_matrix(params[:, :3]).flatten(1), params[:, 3:]], 1)
    compare(
        projection_problem(candidates, joints_2d, mask, frame),
        state,
        lambda step: turn(state, step),
    )
    learnt_pose = torch.randn(3, 14, 3, generator=g, dtype=d) * 300 if learnt else None
    weights = torch.rand(3, 5, generator=g, dtype=d)
    problem = PoseProblem(candidates, weights, 4, proportions, learnt_pose)
    z = torch.randn(3, problem.start().shape[1], generator=g, dtype=d) * 0.3
    compare(
        problem.residuals(params, joints_2d, mask, frame, EnergyWeights(), torch.ones(3, dtype=d)),
        z,
        lambda step: z + step,
    )


def test_rotation_vector_inverts_rotation_matrix():
    g = torch.Generator().manual_seed(2)
    axes = torch.nn.functional.normalize(
        torch.randn(200, 3, generator=g, dtype=torch.float64), dim=-1
    )
    angles = torch.rand(200, 1, generator=g, dtype=torch.float64) * torch.pi
    rotvecs = torch.cat(
        [
            axes * angles,
            torch.tensor([[0.0, 0, 0], [1e-9, 0, 0], [0, 0, -3.14159]], dtype=torch.float64),
        ]
    )
    back = rotation_vector(rotation_matrix(rotvecs))
    torch.testing.assert_close(rotation_matrix(back), rotation_matrix(rotvecs))
    torch.testing.assert_close(back, rotvecs)


def test_scaled_bones_keep_the_root_and_the_directions():
    g = torch.Generator().manual_seed(3)
    poses = torch.randn(4, 14, 3, generator=g, dtype=torch.float64) * 200
    scales = torch.rand(4, len(BONE_GROUPS), generator=g, dtype=torch.float64) + 0.5
    scaled = scaling_map(scales) @ poses
    torch.testing.assert_close(scaling_map(torch.ones_like(scales)) @ poses, poses)
    torch.testing.assert_close(bone_lengths(scaled), bone_scales(scales) * bone_lengths(poses))
    torch.testing.assert_close(hip_midpoint(scaled), hip_midpoint(poses))
    cosine = torch.nn.functional.cosine_similarity(
        bone_vectors(scaled), bone_vectors(poses), dim=-1
    )
    torch.testing.assert_close(cosine, torch.ones_like(cosine))


def test_a_learnt_pose_keeps_its_bones_within_the_band_of_the_neighbours():
    """Each bone's direction kept, its length clamped to within LEARNT_BONE_BAND of the given
    lengths: a bone inside the band unchanged, one outside at its edge."""
    g = torch.Generator().manual_seed(4)
    poses = torch.randn(3, 14, 3, generator=g, dtype=torch.float64) * 200
    own = bone_lengths(poses)
    groups = torch.rand(3, len(BONE_GROUPS), generator=g, dtype=torch.float64) * 3 + 0.2
    factors = bone_scales(groups)  # 0.2-3.2, the two hips alike (the root is their midpoint)
    lengths = own * factors  # own = lengths / factor
    held = within_band(poses, lengths)
    expected = torch.minimum(
        torch.maximum(own, lengths / LEARNT_BONE_BAND), lengths * LEARNT_BONE_BAND
    )
    assert bool(((factors > 1.25) | (factors < 0.8)).any())  # some outside the band
    torch.testing.assert_close(bone_lengths(held), expected)
    torch.testing.assert_close(hip_midpoint(held), hip_midpoint(poses))
    cosine = torch.nn.functional.cosine_similarity(bone_vectors(held), bone_vectors(poses), dim=-1)
    torch.testing.assert_close(cosine, torch.ones_like(cosine))


def test_rotation_matrix_is_orthonormal_and_exact_at_zero():
    r = rotation_matrix(torch.tensor([[0.0, 0.0, 0.0], [0.4, -2.0, 1.0], [1e-7, 0, 0]]))
    torch.testing.assert_close(r @ r.transpose(-1, -2), torch.eye(3).expand(3, 3, 3))
    torch.testing.assert_close(r[0], torch.eye(3))
    half_turn = rotation_matrix(torch.tensor([0.0, torch.pi, 0.0]))
    torch.testing.assert_close(
        half_turn, torch.diag(torch.tensor([-1.0, 1.0, -1.0])), atol=1e-6, rtol=0
    )


def body(seed=0, count=1):
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(1, 14, 3, generator=g) * torch.tensor([200.0, 500.0, 150.0])
    return base + torch.randn(count, 14, 3, generator=g) * 15


@pytest.mark.parametrize("perspective", [True, False])
def test_projection_fit_recovers_a_known_camera(perspective):
    poses = body(count=32)[None]  # (1, 32, 14, 3): near-identical neighbours
    k = torch.tensor([[[1100.0, 0, 500], [0, 1100.0, 510], [0, 0, 1]]]) if perspective else None
    frame = CameraFrame(k, torch.tensor([[480.0, 520.0]]), torch.tensor([90.0]))
    truth = torch.tensor([[0.3, -0.5, 0.2, 0.3, -0.2, 1.6 if perspective else -1.3]])
    joints_2d = project(poses.mean(1, keepdim=True), truth, frame)[:, 0]
    mask = torch.ones(1, 14)
    params = fit_projection(poses, joints_2d, mask, frame, iterations=20)
    start = initial_params(poses, joints_2d, mask, frame)
    fitted_2d = project(poses.mean(1, keepdim=True), params, frame)[:, 0]
    # The neighbours scatter by 15 mm, so the fit of all of them sits within a pixel of the mean.
    assert float((fitted_2d - joints_2d).norm(dim=-1).max()) < 1.0  # px
    assert (
        float(
            (project(poses.mean(1, keepdim=True), start, frame)[:, 0] - joints_2d)
            .norm(dim=-1)
            .max()
        )
        > 5
    )
    torch.testing.assert_close(
        rotation_matrix(params[:, :3]), rotation_matrix(truth[:, :3]), atol=2e-2, rtol=0
    )


def test_top_weighted_follows_eq_wtn():
    scores = torch.tensor([[3.0, -1.0, 7.0, 5.0, 0.0]])
    index, weights = top_weighted(scores, keep=3)
    assert index.tolist() == [[2, 3, 0]]
    torch.testing.assert_close(weights, torch.tensor([[1.0, 0.5, 0.0]]))
    _, tied = top_weighted(torch.ones(1, 4), keep=2)
    torch.testing.assert_close(tied, torch.ones(1, 2))


def test_weighted_pca_ignores_zero_weight_poses():
    poses = body(count=10)[None]
    outlier = poses.clone()
    outlier[:, -1] += 1000
    weights = torch.ones(1, 10)
    weights[:, -1] = 0
    mean, basis, sigma = weighted_pca(outlier, weights, components=4)
    assert bool((sigma[:, :-1] >= sigma[:, 1:]).all())
    torch.testing.assert_close(mean, poses[:, :9].flatten(-2).mean(1), atol=1e-3, rtol=0)
    torch.testing.assert_close(
        basis @ basis.transpose(-1, -2), torch.eye(4)[None], atol=1e-5, rtol=0
    )


def _pinhole_projection(points: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """(B, J, 3) camera coordinates, (B, 3, 3) K -> (B, J, 2) px."""
    image = points @ k.transpose(-1, -2)
    return image[..., :2] / image[..., 2:]


def test_a_perspective_fit_places_the_points_it_projects():
    torch.manual_seed(0)
    k = torch.tensor([[1100.0, 0, 500], [0, 1150.0, 480], [0, 0, 1]]).expand(4, 3, 3)
    frame = CameraFrame(k, torch.zeros(4, 2), torch.full((4,), 80.0))
    params = torch.cat(
        [0.3 * torch.randn(4, 3), 0.5 * torch.randn(4, 2), 1.5 + 0.1 * torch.randn(4, 1)], -1
    )
    points = 300 * torch.randn(4, 1, 14, 3)
    rotated = points[:, 0] @ rotation_matrix(params[:, :3]).transpose(-1, -2)
    placed = rotated + camera_translation(params[:, 3:], frame, k)[:, None]
    torch.testing.assert_close(
        _pinhole_projection(placed, k), project(points, params, frame)[:, 0], atol=1e-3, rtol=0
    )


def test_a_weak_perspective_fit_is_placed_where_a_camera_draws_it_at_its_scale():
    """X's origin lands where M draws it, at the depth where a millimetre spans M's pixels."""
    frame = CameraFrame(None, torch.tensor([[320.0, 200.0]]), torch.tensor([60.0]))
    params = torch.tensor([[0.1, -0.2, 0.3, 0.4, -0.7, 0.2]])
    k = torch.tensor([[[900.0, 0, 300], [0, 900.0, 250], [0, 0, 1]]])
    origin = camera_translation(params[:, 3:], frame, k)  # (1, 3)
    step = torch.tensor([[[0.0, 0.0, 0.0], [10.0, -5.0, 0.0]]])  # mm, at the origin's depth
    drawn = _pinhole_projection(origin[:, None] + step, k)[0]
    weak = project(step[:, None] @ rotation_matrix(params[:, :3]), params, frame)[0, 0]
    torch.testing.assert_close(drawn, weak, atol=1e-3, rtol=0)
