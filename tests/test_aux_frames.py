"""Aux frames: random resets and arm placements whose object state trains the read-out beside the demonstrations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import DEMO_ENV_KWARGS

from dust_rl.agents import DustConfig, DustPolicy, make_policy
from dust_rl.agents.heads.attention_pooling import WIDTH
from dust_rl.data import DemoDataset
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.data.features import dataset_policy_kwargs, env_state_width
from dust_rl.envs.factory import make_env
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY, STATE_KEY
from dust_rl.train.readout.aux_frames import (
    FIRST_SEED,
    AuxFrameBatches,
    _close_up_targets,
    _walk_targets,
    render_aux_frames,
)

pytestmark = pytest.mark.usefixtures("one_thread")
ENV_ID = "DustFranka-v0"


def test_frames_are_seeded_padded_and_show_the_reset_objects():
    tasks, width = ["pick_place", "press_button"], 16
    rows, instructions = render_aux_frames(ENV_ID, DEMO_ENV_KWARGS, tasks, ["front"], 4, width, progress=False)
    again, _ = render_aux_frames(ENV_ID, DEMO_ENV_KWARGS, tasks, ["front"], 4, width, progress=False)
    other, _ = render_aux_frames(ENV_ID, DEMO_ENV_KWARGS, tasks, ["front"], 4, width, seed=1, progress=False)
    frames = rows.get((*IMAGE_KEY, "front"))
    assert frames.dtype == torch.uint8 and frames.shape[:2] == (4, 3) and len(instructions) == 4
    assert torch.equal(frames, again.get((*IMAGE_KEY, "front")))  # bit for bit
    assert not torch.equal(frames, other.get((*IMAGE_KEY, "front")))
    state = rows.get(ENV_STATE_KEY)
    assert state.shape == (4, width)
    env = make_env(ENV_ID, {**DEMO_ENV_KWARGS, "task": "pick_place"})
    obs, _ = env.reset(seed=FIRST_SEED)  # frame 0: pick_place; the objects rest until the arm meets them
    env.close()
    reset_state = torch.from_numpy(obs["observation.environment_state"])
    plate = slice(6, 9)  # the plate is a mocap body: random actions never move it
    assert torch.equal(state[0, plate], reset_state[plate]) and not state[0, 13:].any()  # zero padding


def test_readout_loss_trains_the_pixel_keypoints(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)
    width = env_state_width(dataset)
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, keypoints=2,
                         keypoint_source="pixels", aux_state_dim=width, lambda_aux=1.0)
    rows, instructions = render_aux_frames(ENV_ID, dataset.meta["env_kwargs"], dataset.tasks, policy.cameras, 3,
                                           width, progress=False)
    batches = AuxFrameBatches(rows, instructions, policy, EnvStateNorm.of_dataset(dataset))
    frames = batches.sample(5)
    assert frames.get("pixels").shape[:3] == (5, len(policy.cameras), 3) and frames.get("env_state").shape == (5, width)
    loss = policy.readout_loss(frames, torch.Generator().manual_seed(0))
    loss.backward()
    assert loss > 0 and all(p.grad is not None for p in policy.condition.keypoints.parameters())
    assert all(p.grad is not None for p in policy.state_readout.parameters())
    on_features = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                              horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, keypoints=2,
                              aux_state_dim=width, lambda_aux=1.0)
    with pytest.raises(ValueError, match="needs a state read-out on the image tokens"):
        on_features.readout_loss(frames)



def test_token_readout_learns_from_the_frames_frozen_tokens(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)
    width = env_state_width(dataset)
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, readout="tokens",
                         readout_heads=3, aux_state_dim=width, lambda_aux=1.0,
                         aux_state_input=True)
    rows, instructions = render_aux_frames(ENV_ID, dataset.meta["env_kwargs"], dataset.tasks, policy.cameras, 3,
                                           width, progress=False)
    batches = AuxFrameBatches(rows, instructions, policy, EnvStateNorm.of_dataset(dataset))
    everything = batches.rows(torch.arange(3))
    assert "pixels" not in everything.keys()
    torch.testing.assert_close(everything.get("image_tokens"), policy.frame_tokens(policy.frames(rows)),
                               rtol=0, atol=0)
    loss = policy.readout_loss(batches.sample(5))
    loss.backward()
    assert loss > 0 and all(p.grad is not None for p in policy.state_readout.parameters())
    assert policy.state_readout.pool.attend.out_features == 3  # one attention pooling per head
    assert policy.state_readout.pool.head[0].in_features == 3 * WIDTH  # the heads' pooled vectors side by side
    assert all(p.grad is None for p in (*policy.model.parameters(), *policy.condition.parameters()))
    # The trunk reads the estimate after the robot state: the state token embeds both.
    assert policy.model.state_in.in_features == policy.config.state_dim + width


def test_a_finer_readout_grid_feeds_the_readout_more_tokens_and_the_trunk_the_same(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)

    def build(**grid) -> DustPolicy:
        torch.manual_seed(0)  # the read-out is built after the trunk: both policies' trunks are the same
        return make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                           horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, vision_grid=(2, 2),
                           cond_grid=(2, 2), readout="tokens", aux_state_dim=env_state_width(dataset),
                           lambda_aux=1.0, **grid)

    fine, coarse = build(readout_grid=(4, 4)), build()
    frames = torch.randint(0, 256, (3, len(fine.cameras), 3, 32, 32), dtype=torch.uint8)
    text, mask = fine.backbone.text_tokens(["press the red button"] * 3)
    state = torch.zeros(3, fine.config.state_dim)
    batches = [policy.feature_batch(policy.frame_tokens(frames), text, mask, state) for policy in (fine, coarse)]
    assert [b.get("image_tokens").shape[-2] for b in batches] == [16, 4]
    assert fine.state_readout.pool.position.shape[0] == len(fine.cameras) * 16
    conditions = [policy._model_batch(b).get("cond_tokens") for policy, b in zip((fine, coarse), batches)]
    torch.testing.assert_close(*conditions)
    with pytest.raises(ValueError, match="readout_grid belongs to the token read-out"):
        DustConfig(readout_grid=(8, 8))
    with pytest.raises(ValueError, match=r"readout_grid \(6, 6\) must be a multiple of cond_grid \(4, 4\)"):
        DustConfig(readout="tokens", cond_grid=(4, 4), readout_grid=(6, 6))


def test_close_ups_put_the_gripper_over_what_the_task_is_about():
    """Half of pick_place's expert plan is over the cube or the plate (hover, grasp, place, retreat), the rest
    lifts and carries between them; a walk from home seldom ends within 3 cm of either."""
    env = make_env(ENV_ID, {**DEMO_ENV_KWARGS, "task": "pick_place"})
    sim, near = env.unwrapped, {}
    for kind, targets in (("walk", _walk_targets), ("close-up", _close_up_targets)):
        distances = []
        for seed in range(16):
            sim.reset_unobserved(seed=FIRST_SEED + seed)
            sim.place_end_effectors(*targets(sim, np.random.default_rng(seed)))
            cube_and_plate = sim.task.environment_state(sim.data)[:9].reshape(3, 3)[[0, 2], :2]  # xyz first
            distances.append(np.linalg.norm(cube_and_plate - sim.end_effector_pose()[0][:2], axis=1).min())
        near[kind] = np.mean(np.array(distances) < 0.03)
    env.close()
    assert near["close-up"] >= 0.4 and near["walk"] <= 0.2, near


def test_the_token_readout_can_read_the_robot_state_and_attend_over_the_instruction(demo_dir, tiny_encoder, minilm):
    dataset = DemoDataset(demo_dir)
    width = env_state_width(dataset)
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, readout="tokens",
                         aux_state_dim=width, lambda_aux=1.0, readout_heads=2, readout_proprio=True,
                         readout_text="attention")
    rows, instructions = render_aux_frames(ENV_ID, dataset.meta["env_kwargs"], dataset.tasks, policy.cameras, 3,
                                           width, progress=False)
    batches = AuxFrameBatches(rows, instructions, policy, EnvStateNorm.of_dataset(dataset))
    frames = batches.rows(torch.arange(3))
    torch.testing.assert_close(frames.get("state"), policy.normalizer.normalize_state(rows.get(STATE_KEY)))
    policy.readout_loss(frames).backward()
    readout = policy.state_readout
    assert readout.text_attend.weight.grad.abs().sum() > 0 and readout.text_query.weight.grad.abs().sum() > 0
    assert readout.pool.condition.in_features == policy.backbone.text_dim + policy.config.state_dim
    with torch.no_grad():
        estimate = readout(frames.get("image_tokens"), frames.get("text_tokens"), frames.get("text_mask"),
                           frames.get("state"))
        moved = readout(frames.get("image_tokens"), frames.get("text_tokens"), frames.get("text_mask"),
                        frames.get("state") + 1.0)
        padded = frames.get("text_tokens").masked_fill(~frames.get("text_mask")[..., None], 1e3)
        same = readout(frames.get("image_tokens"), padded, frames.get("text_mask"), frames.get("state"))
    assert not torch.allclose(estimate, moved)  # where the hand is changes where the objects are read
    torch.testing.assert_close(same, estimate)  # padding tokens carry no weight
    with pytest.raises(ValueError, match="readout_proprio belongs to the token read-out"):
        DustConfig(readout_proprio=True)
    with pytest.raises(ValueError, match="unknown readout_text 'max'"):
        DustConfig(readout="tokens", readout_text="max")
