"""Spatial-softmax keypoints, the condition tokens they add, and the privileged-state read-out that trains them."""

from __future__ import annotations

import pytest
import torch
from test_agents_policy import observation, perturb, tiny_policy

from dust_rl.agents import DustConfig, load_policy, make_policy, save_policy
from dust_rl.agents.condition import ConditionProjector
from dust_rl.agents.heads.keypoints import SpatialKeypoints
from dust_rl.data import DatasetError, DemoDataset, DemoWindows
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.data.features import FeatureCache, dataset_policy_kwargs

pytestmark = pytest.mark.usefixtures("one_thread")


def peak_finder(channels: int) -> SpatialKeypoints:
    """One keypoint whose heat map is channel 0 of the features, made sharp: it sits on that channel's peak."""
    head = SpatialKeypoints(channels, 1).double()
    first, _, second = head.heat
    with torch.no_grad():
        for conv in (first, second):
            conv.weight.zero_()
            conv.bias.zero_()
        first.weight[0, 0, 1, 1] = 1.0  # centre tap of the 3x3 convolution
        second.weight[0, 0] = 1.0
        head.log_temperature.fill_(6.0)  # peak logit GELU(1) * e^6 ~ 339: the other cells weigh ~e^-339
    return head


@pytest.mark.parametrize(("row", "col"), [(0, 0), (2, 5), (4, 1)])
def test_keypoint_sits_on_the_peak_cell_centre(row, col):
    rows, cols, channels = 5, 6, 3
    features = torch.zeros(1, channels, rows, cols, dtype=torch.float64)
    features[0, 0, row, col] = 1.0
    features[0, 1:] = torch.arange(rows * cols, dtype=torch.float64).view(rows, cols)
    coordinates, attended = peak_finder(channels)(features)
    expected_x, expected_y = (2 * col + 1) / cols - 1, (2 * row + 1) / rows - 1  # cell centres on [-1, 1]
    tolerance = 1e-9  # the other cells weigh ~e^-339, far below float64 rounding
    torch.testing.assert_close(coordinates[0, 0], torch.tensor([expected_x, expected_y], dtype=torch.float64),
                               rtol=0, atol=tolerance)
    torch.testing.assert_close(attended[0, 0], features[0, :, row, col], rtol=0, atol=tolerance)


def test_keypoint_interpolates_between_cells():
    """Two equally hot neighbouring cells put the keypoint on their shared edge: finer than the grid."""
    features = torch.zeros(1, 1, 4, 4, dtype=torch.float64)
    features[0, 0, 1, 1] = features[0, 0, 1, 2] = 1.0
    coordinates, _ = peak_finder(1)(features)
    torch.testing.assert_close(coordinates[0, 0], torch.tensor([0.0, -0.25], dtype=torch.float64), rtol=0, atol=1e-9)


def test_projector_appends_one_token_per_camera_keypoint():
    cameras, grid, dim, keypoints = 2, (3, 4), 8, 5
    projector = ConditionProjector(cameras, grid, dim, text_dim=6, cond_dim=16, n_keypoints=keypoints)
    image, text = torch.randn(2, cameras, 12, dim), torch.randn(2, 7, 6)
    mask = torch.tensor([[True] * 7, [True] * 3 + [False] * 4])
    tokens, token_mask = projector(image, text, mask)
    assert tokens.shape == (2, cameras * (12 + keypoints) + 7, 16)
    assert token_mask[:, :cameras * (12 + keypoints)].all() and torch.equal(token_mask[:, -7:], mask)
    points = projector.keypoint_features(image)
    assert points.shape == (2, cameras * keypoints, 2 + dim) and points[..., :2].abs().max() <= 1
    # Each camera's keypoints come from that camera's map only.
    moved = image.clone()
    moved[:, 1] = torch.randn_like(moved[:, 1])
    changed = projector.keypoint_features(moved)
    assert torch.equal(changed[:, :keypoints], points[:, :keypoints])
    assert not torch.equal(changed[:, keypoints:], points[:, keypoints:])


def test_config_checks_keypoint_settings():
    with pytest.raises(ValueError, match="aux_state_dim with readout 'keypoints' needs keypoints"):
        DustConfig(aux_state_dim=9, lambda_aux=1.0)
    assert DustConfig(aux_state_dim=9, lambda_aux=1.0, readout="tokens").readout_inputs_exist
    with pytest.raises(ValueError, match="unknown readout 'pixels'"):
        DustConfig(readout="pixels")
    with pytest.raises(ValueError, match=r"readout_heads must be an int in \[1, 64\]"):
        DustConfig(readout="tokens", readout_heads=0)
    with pytest.raises(ValueError, match=r"keypoints must be an int in \[0, 256\]"):
        DustConfig(keypoints=-1)
    with pytest.raises(ValueError, match="lambda_aux must be a finite number"):
        DustConfig(keypoints=4, aux_state_dim=3, lambda_aux=float("nan"))
    with pytest.raises(ValueError, match="aux_state_input needs aux_state_dim"):
        DustConfig(keypoints=4, aux_state_input=True)
    with pytest.raises(ValueError, match="keypoint_source 'pixels' needs keypoints"):
        DustConfig(keypoint_source="pixels")
    with pytest.raises(ValueError, match="unknown keypoint_source 'depth'"):
        DustConfig(keypoints=4, keypoint_source="depth")
    with pytest.raises(ValueError, match="aux_state_dim needs lambda_aux > 0"):
        DustConfig(keypoints=4, aux_state_dim=3)
    read_out = {"state_dim": 8, "keypoints": 4, "aux_state_dim": 3, "lambda_aux": 1.0}
    fed = DustConfig(**read_out, aux_state_input=True)
    assert fed.trunk_state_dim == 11 and DustConfig(**read_out).trunk_state_dim == 8


@pytest.mark.parametrize(("source", "aux_state_input"), [("features", False), ("features", True), ("pixels", True)])
def test_keypoint_policy_round_trips_and_its_heads_get_gradients(source, aux_state_input, tiny_encoder, minilm,
                                                                 tmp_path):
    policy = tiny_policy("dust", tiny_encoder, minilm, keypoints=3, keypoint_source=source, aux_state_dim=4,
                         lambda_aux=1.0, aux_state_input=aux_state_input)
    perturb(policy)
    features = policy.observation_features(observation())
    batch = features.set("action_chunk", torch.randn(2, 6, 3)).set(
        "future_tokens", policy.future_targets(features.get("image_tokens")))
    losses = policy.compute_loss(batch, torch.Generator().manual_seed(0))
    assert "loss_aux" not in losses.keys()  # no privileged state in the batch: no auxiliary loss
    batch.set("env_state", torch.randn(2, 4))
    losses = policy.compute_loss(batch, torch.Generator().manual_seed(0))
    assert policy.estimate_env_state(batch).shape == (2, 4)
    expected = losses["loss_action"] + losses["loss_vision"] + losses["loss_aux"]  # lambda_wm = lambda_aux = 1
    torch.testing.assert_close(losses["loss"], expected)
    losses["loss"].backward()
    for module in (policy.condition.keypoints, policy.state_readout):
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in module.parameters())
    # The read-out head is the policy's own modules under the names policy files store them by.
    assert policy.readout.network is policy.state_readout and policy.readout.keypoints is policy.condition.keypoints
    assert policy.readout.reads_frames == (source == "pixels")
    # Training optimises exactly the trainable parameters, the read-out among them.
    trained = {id(p) for p in policy.trainable_modules().parameters()}
    assert trained == {id(p) for p in policy.trainable_parameters()}
    loaded = load_policy(save_policy(policy, tmp_path / "policy.pt"))
    assert (loaded.config.keypoints, loaded.config.keypoint_source, loaded.config.aux_state_dim) == (3, source, 4)
    obs = observation()
    expected_plan = policy.plan(obs, torch.Generator().manual_seed(1))
    assert torch.equal(loaded.plan(obs, torch.Generator().manual_seed(1))["action_chunk"],
                       expected_plan["action_chunk"])
    # The estimate reaches the actions exactly when it is fed to the trunk.
    with torch.no_grad():
        loaded.state_readout.mlp[-1].bias.add_(1.0)
    moved = loaded.plan(obs, torch.Generator().manual_seed(1))["action_chunk"]
    assert torch.equal(moved, expected_plan["action_chunk"]) != aux_state_input


def test_feature_batches_carry_the_normalised_environment_state(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)
    width = len(dataset.meta["stats"]["observation.environment_state"]["mean"])
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, keypoints=2,
                         aux_state_dim=width, lambda_aux=1.0)
    cache = FeatureCache(dataset, policy, progress=False)
    windows = DemoWindows(dataset, horizon=6, batch_size=5).sample()
    raw = windows.get(("observation", "environment_state")).float()
    task = dataset.row_task_index[windows.get("index")]
    estimate = cache.batch(windows).get("env_state")
    torch.testing.assert_close(EnvStateNorm.of_dataset(dataset).denormalize(estimate, task), raw)
    dataset.meta["stats"].pop("observation.environment_state")  # as in a LeRobot dataset from elsewhere
    with pytest.raises(DatasetError, match="no observation.environment_state"):
        FeatureCache(dataset, policy, progress=False)
    without = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                          horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0)
    assert without.readout is None
    with pytest.raises(ValueError, match="no state read-out"):
        without.estimate_env_state(cache.batch(windows))
