import pytest
import torch

from ds3d.fit.camera import CameraFrame, initial_params, project, rotation_matrix
from ds3d.fit.lbfgs import minimize
from ds3d.fit.selection import top_weighted
from ds3d.fit.solve import fit_projection, weighted_pca


def quadratic_problems(batch=6, dim=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(batch, dim, dim, generator=g)
    a = a @ a.transpose(1, 2) + 0.5 * torch.eye(dim) * torch.arange(1, batch + 1)[:, None, None]
    b = torch.randn(batch, dim, generator=g)

    def energy(x):
        return 0.5 * (x[:, None] @ a @ x[:, :, None])[:, 0, 0] - (b * x).sum(-1)

    return energy, torch.linalg.solve(a, b)


def test_batched_lbfgs_solves_each_problem_independently():
    energy, solution = quadratic_problems()
    x, _ = minimize(energy, torch.zeros_like(solution), iterations=50)
    torch.testing.assert_close(x, solution, atol=1e-3, rtol=0)


def test_batched_lbfgs_rosenbrock_and_never_increases_the_energy():
    target = torch.tensor([1.0, 2.0, -0.5])

    def rosenbrock(x):
        return (target - x[:, 0]) ** 2 + 100 * (x[:, 1] - x[:, 0] ** 2) ** 2

    start = torch.zeros(3, 2)
    x, _ = minimize(rosenbrock, start, iterations=200)
    torch.testing.assert_close(x[:, 0], target, atol=1e-3, rtol=0)
    _, short_value = minimize(rosenbrock, start, iterations=3)
    assert bool((short_value <= rosenbrock(start)).all())


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
    params, residuals = fit_projection(poses, joints_2d, mask, frame, iterations=100)
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
    assert residuals.shape == (1, 32)


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
