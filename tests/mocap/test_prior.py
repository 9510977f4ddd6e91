import functools

import torch

from ds3d.fit.camera import rotation_matrix
from ds3d.mocap.database import PoseDatabase
from ds3d.mocap.normalize import normalize_2d
from ds3d.mocap.prior import (
    FEATURES,
    NETWORKS,
    NOISE_GATE,
    PACKED_SIDE,
    LiftingPrior,
    PriorShape,
    ResidualMLP,
    camera_rays,
    folded,
    lifted,
    look_at,
    mirrored,
    packed,
    prior_features,
    query_view,
    unpacked,
)
from ds3d.skeleton import FLIP, L_HIP, NUM_JOINTS, R_HIP
from ds3d.util.paths import MODELS_DIR


def bundled_poses(n: int) -> torch.Tensor:
    """n body-frame poses of the bundled database (mm)."""
    return PoseDatabase.load(MODELS_DIR / "posedb").poses[:n]


def pairwise(points: torch.Tensor) -> torch.Tensor:
    return torch.cdist(points, points)


def small_nets(seed: int = 0) -> dict[str, ResidualMLP]:
    torch.manual_seed(seed)
    lifting = PriorShape(width=32, blocks=1)
    noise = PriorShape(width=16, blocks=1, dropout=0.0, outputs=1)
    return {name: ResidualMLP(noise if name == "noise" else lifting).eval() for name in NETWORKS}


def a_query(b: int = 5):
    joints_2d = torch.rand(b, NUM_JOINTS, 2) * 300
    visible = torch.ones(b, NUM_JOINTS, dtype=torch.bool)
    k = torch.tensor([[1000.0, 0, 150], [0, 1000, 150], [0, 0, 1]]).expand(b, 3, 3)
    return joints_2d, visible, k


def test_look_at_sees_a_person_off_the_optical_axis_as_one_on_it():
    """A camera turned about its centre sees the same person as one looking straight at them,
    up to a turn of the image about its centre: every distance between joints is the same."""
    pose = bundled_poses(3) + torch.tensor([0.0, 0.0, 4000.0])
    visible = torch.ones(3, NUM_JOINTS, dtype=torch.bool)
    aside = rotation_matrix(torch.tensor([[0.3, -0.4, 0.1], [0.0, 0.5, 0.0], [-0.2, 0.0, 0.7]]))
    straight, _ = look_at(pose, visible)
    turned_away, turn = look_at(pose @ aside.transpose(-1, -2), visible)
    torch.testing.assert_close(pairwise(turned_away), pairwise(straight), atol=1e-5, rtol=1e-4)
    # the turn takes the joints' mean direction onto the optical axis
    rays = pose @ aside.transpose(-1, -2)
    unit = rays / rays.norm(dim=-1, keepdim=True)
    centre = torch.nn.functional.normalize(unit.mean(1), dim=-1)
    torch.testing.assert_close(
        (turn @ centre[..., None])[..., 0],
        torch.tensor([[0.0, 0, 1]]).expand(3, 3),
        atol=1e-6,
        rtol=0,
    )


def test_camera_rays_undo_the_intrinsics():
    k = torch.tensor([[1100.0, 0, 500], [0, 1000, 480], [0, 0, 1]]).expand(2, 3, 3)
    points = torch.randn(2, NUM_JOINTS, 3) * 300 + torch.tensor([100.0, -50, 5000])
    pixels = (points @ k.transpose(-1, -2))[..., :2] / points[..., 2:]
    rays = camera_rays(pixels, k)
    torch.testing.assert_close(rays, points / points[..., 2:], atol=1e-5, rtol=1e-5)


def test_a_singular_camera_gives_finite_rays():
    k = torch.zeros(2, 3, 3)
    k[1] = torch.tensor([[1000.0, 0, 500], [0, 1000, 500], [0, 0, 1]])
    pixels = torch.rand(2, NUM_JOINTS, 2) * 1000
    rays = camera_rays(pixels, k)
    assert bool(torch.isfinite(rays).all())
    torch.testing.assert_close(rays[0, :, :2], pixels[0])  # as if K were the identity
    torch.testing.assert_close(rays[1, :, :2], (pixels[1] - 500) / 1000)


def test_features_are_the_normalised_visible_joints_and_their_flags():
    points = torch.rand(4, NUM_JOINTS, 2) * 200
    visible = torch.rand(4, NUM_JOINTS) > 0.3
    features = prior_features(points, visible)
    assert features.shape == (4, 3 * NUM_JOINTS)
    coordinates = features[:, : 2 * NUM_JOINTS].unflatten(1, (NUM_JOINTS, 2))
    torch.testing.assert_close(coordinates, normalize_2d(points, visible))
    assert bool((coordinates[~visible] == 0).all())
    assert torch.equal(features[:, 2 * NUM_JOINTS :], visible.float())


def test_mirrored_twice_is_the_pose():
    pose = bundled_poses(2)
    once = mirrored(pose)
    assert torch.equal(once[:, list(FLIP), 0], -pose[:, :, 0])
    assert torch.equal(mirrored(once), pose)


def test_packing_rounds_each_hidden_weight_by_at_most_half_its_rows_step():
    net = ResidualMLP(PriorShape(width=PACKED_SIDE, blocks=1))
    state = net.state_dict()
    stored = packed(state)
    restored = unpacked(stored)
    assert restored.keys() == state.keys()
    for name, value in state.items():
        if value.dim() == 2 and min(value.shape) >= PACKED_SIDE:  # the hidden layers'
            assert stored[name].dtype == torch.int8
            step = value.abs().amax(1, keepdim=True) / 127
            assert bool(((restored[name] - value).abs() <= step / 2 + 1e-7).all()), name
        elif value.is_floating_point():
            torch.testing.assert_close(restored[name], value.half().float())
        else:
            assert torch.equal(restored[name], value)


def test_a_saved_prior_loads_with_its_packed_weights(tmp_path):
    nets = small_nets()
    prior = LiftingPrior(nets, {"seed": 0})
    prior.save(tmp_path / "prior")
    loaded = LiftingPrior.load(tmp_path / "prior")
    # what was saved: the weights packed
    rounded = small_nets(seed=1)
    for name, net in rounded.items():
        net.load_state_dict(unpacked(packed(nets[name].state_dict())))
    query = a_query()
    expected = LiftingPrior(rounded, prior.manifest)(*query)
    answer = loaded(*query)
    torch.testing.assert_close(answer, expected)
    assert loaded.manifest == prior.manifest and loaded.digest == prior.digest
    # rooted at the hip midpoint
    torch.testing.assert_close((answer[:, R_HIP] + answer[:, L_HIP]) / 2, torch.zeros(5, 3))


def test_the_estimated_noise_level_blends_the_clean_and_the_noisy_networks_pose():
    """An estimate of zero gives the clean network's pose, one at NOISE_GATE or above the
    noisy one's, one between a linear blend of the two; a pose with a hidden joint gets the
    noisy one's."""
    nets = small_nets()
    query = a_query()
    points, turn = query_view(*query)
    features = prior_features(points, query[1])

    def answer(estimate: float) -> torch.Tensor:
        torch.nn.init.zeros_(nets["noise"].head.weight)
        torch.nn.init.constant_(nets["noise"].head.bias, estimate)
        return LiftingPrior(nets, {})(*query)

    def alone(name: str) -> torch.Tensor:
        with torch.inference_mode():
            pose = lifted(nets[name], features) @ turn
        return pose - (pose[:, R_HIP] + pose[:, L_HIP])[:, None] / 2

    clean, noisy = alone("clean"), alone("noisy")
    close = functools.partial(torch.testing.assert_close, atol=1e-3, rtol=1e-5)  # mm, float32
    assert float((clean - noisy).abs().max()) > 1.0  # mm: the two differ
    close(answer(-0.01), clean)
    close(answer(0.0), clean)
    close(answer(NOISE_GATE), noisy)
    close(answer(2 * NOISE_GATE), noisy)
    close(answer(NOISE_GATE / 4), 0.75 * clean + 0.25 * noisy)
    # a pose with a hidden joint: the noisy network's alone, whatever the estimate
    hidden = query[1].clone()
    hidden[2, 5] = False
    query = (query[0], hidden, query[2])
    points, turn = query_view(*query)
    features = prior_features(points, hidden)
    blended = answer(0.0)
    close(blended[2], alone("noisy")[2])
    close(blended[[0, 1, 3, 4]], alone("clean")[[0, 1, 3, 4]])


def test_a_folded_network_answers_as_the_network_does_in_eval_mode():
    """folded: each batch norm folded into its linear layer, the dropouts gone: the same
    function, up to float32's rounding of the folded weights."""
    torch.manual_seed(0)
    net = ResidualMLP(PriorShape(width=32, blocks=2))
    for module in net.modules():  # statistics and affine maps other than the initial identity
        if isinstance(module, torch.nn.BatchNorm1d):
            module.running_mean.uniform_(-1, 1)
            module.running_var.uniform_(0.5, 2)
            torch.nn.init.uniform_(module.weight, 0.5, 1.5)
            torch.nn.init.uniform_(module.bias, -0.5, 0.5)
    net.eval()
    fused = folded(net)
    kinds = (torch.nn.BatchNorm1d, torch.nn.Dropout)
    assert not any(isinstance(module, kinds) for module in fused.modules())
    features = torch.randn(8, FEATURES)
    with torch.no_grad():
        torch.testing.assert_close(fused(features), net(features), rtol=1e-4, atol=1e-4)


def test_a_prior_moved_to_a_device_is_a_copy():
    """Lifter(device=...) moves its prior there; the prior it was given stays where it was."""
    prior = LiftingPrior(small_nets(), {})
    moved = prior.to("cpu")
    for name in NETWORKS:
        assert moved.nets[name] is not prior.nets[name]
        assert moved.running[name] is not prior.running[name]
    torch.nn.init.zeros_(moved.running["clean"].head.weight)  # changing the copy's
    query = a_query()
    assert not torch.equal(moved(*query), prior(*query))
