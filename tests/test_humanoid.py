"""DustHumanoid-v0 (Unitree G1 with Dex3 hands) keeps DustFranka-v0's API guarantees.

Suite-wide behaviour (experts, dense rewards, cameras showing the task) is
tested for both robots in test_experts.py and test_images.py.
"""

from __future__ import annotations

import gymnasium as gym
import mink
import mujoco
import numpy as np
import pytest
from conftest import HUMANOID_TASKS, assert_same_observations, seeded_rollout
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from torchrl.envs import GymEnv
from torchrl.envs.utils import check_env_specs

from dust_rl.envs import DustEnv
from dust_rl.envs.env import MAX_TRANSLATION
from dust_rl.envs.rendering import COLLISION_GROUP, VISUAL_GROUP

ACTION_DIM = 14  # (left: translation 3, rotation 3, closure 1), then the same for the right hand
STATE_DIM = 17 + 14 + 2 * 8  # waist and arm joints, finger joints, per hand (pos, quat, opening)


@pytest.fixture(scope="module")
def humanoid_env():
    env = DustEnv(task="pick_place", robot="humanoid", obs_mode="state")
    yield env
    env.close()


def _step(env: DustEnv, action: np.ndarray, steps: int) -> dict:
    for _ in range(steps):
        obs = env.step(np.asarray(action, np.float32))[0]
    return obs


def test_registration_and_suite():
    assert set(HUMANOID_TASKS) == {"pick_place", "place_in_basket", "handover", "lift_box", "push", "open_lid"}
    env = gym.make("DustHumanoid-v0", task="handover", obs_mode="state")
    assert env.unwrapped.robot.name == "humanoid" and env.unwrapped.task.robot == "humanoid"
    assert env.action_space.shape == (ACTION_DIM,)
    env.close()
    with pytest.raises(ValueError, match="lift_box"):
        gym.make("DustHumanoid-v0", task="press_button")  # a Franka task: the error lists the humanoid suite


def test_gymnasium_check_env_rgb():
    env = DustEnv(task="lift_box", robot="humanoid", image_size=32, render_mode="rgb_array")
    gym_check_env(env, skip_render_check=False)
    env.close()


def test_gymnasium_and_sb3_check_env_state(humanoid_env):
    gym_check_env(humanoid_env, skip_render_check=True)
    sb3_check_env(humanoid_env, warn=True, skip_render_check=True)


def test_torchrl_check_env_specs_gymenv():
    env = GymEnv("DustHumanoid-v0", task="push", image_size=32)
    check_env_specs(env, seed=0)
    env.close()


def test_observation_layout_and_head_camera():
    env = DustEnv(task="handover", robot="humanoid", image_size=48, render_mode="rgb_array")
    obs, info = env.reset(seed=2)
    assert env.cameras == ("head",)
    assert obs["observation.image.head"].shape == (48, 48, 3) and obs["observation.image.head"].dtype == np.uint8
    state = obs["observation.state"]
    assert state.shape == (STATE_DIM,) and state.dtype == np.float32
    for hand, (pos, _) in enumerate(env.end_effector_poses()):  # left hand's block first
        block = state[STATE_DIM - 16 + 8 * hand:][:8]
        np.testing.assert_allclose(block[:3], pos, rtol=np.finfo(np.float32).eps, atol=0)  # float32 copy of pos
        assert block[7] == pytest.approx(0.0, abs=0.05)  # open hand
    assert "bottle" in obs["language_instruction"] == info["language_instruction"]
    assert np.array_equal(env.render(), obs["observation.image.head"])
    env.close()
    wrists = DustEnv(task="push", robot="humanoid", image_size=32, cameras=("head", "left_wrist", "right_wrist"))
    obs, _ = wrists.reset(seed=0)
    assert all(obs[f"observation.image.{c}"].std() > 5 for c in wrists.cameras)
    wrists.close()


def test_same_seed_bit_for_bit_in_separate_envs():
    first, second = (DustEnv(task="open_lid", robot="humanoid", image_size=32, reward_type="dense") for _ in range(2))
    obs_a, rewards_a = seeded_rollout(first, seed=5, steps=25)
    obs_b, rewards_b = seeded_rollout(second, seed=5, steps=25)
    assert rewards_a == rewards_b and len(obs_a) > 10
    assert_same_observations(obs_a, obs_b)
    other, _ = seeded_rollout(first, seed=6, steps=1)
    assert not np.array_equal(other[0]["observation.environment_state"], obs_a[0]["observation.environment_state"])


@pytest.mark.parametrize("action", [np.full(ACTION_DIM, np.nan), np.zeros(7), np.zeros(ACTION_DIM + 1)],
                         ids=["nan", "one-arm", "too-long"])
def test_bad_actions_raise(humanoid_env, action):
    humanoid_env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN|shape"):
        humanoid_env.step(action.astype(np.float32))


def test_ik_failure_truncates_episode():
    env = DustEnv(task="push", robot="humanoid", obs_mode="state")
    env.reset(seed=0)
    # A real, infeasible QP: joint limits that exclude the robot's current configuration.
    model = env.controller.model
    saved = model.jnt_range.copy()
    elbow = model.joint("g1/left_elbow_joint").id
    model.jnt_range[elbow] = (2.0, 2.05)
    env.controller.limits.append(mink.ConfigurationLimit(model))
    model.jnt_range[:] = saved
    _, reward, terminated, truncated, info = env.step(np.zeros(ACTION_DIM, np.float32))
    assert truncated and not terminated and reward == 0.0
    assert info["truncation_reason"] == "ik_failure"


def test_make_vec_async():
    envs = gym.make_vec("DustHumanoid-v0", num_envs=2, vectorization_mode="async", task="lift_box", obs_mode="state")
    obs, _ = envs.reset(seed=[0, 1])
    obs, reward, terminated, truncated, info = envs.step(np.zeros((2, ACTION_DIM), np.float32))
    assert obs["agent_pos"].shape == (2, STATE_DIM)
    assert reward.shape == (2,) and info["task"].tolist() == ["lift_box", "lift_box"]
    envs.close()


def test_action_layout_left_hand_then_right_hand(humanoid_env):
    """Numbers 0-6 drive the left hand, 7-13 the right: each moves and closes only its own hand."""
    for hand in (0, 1):
        humanoid_env.reset(seed=0)
        before = [pos for pos, _ in humanoid_env.end_effector_poses()]
        action = np.zeros(ACTION_DIM)
        action[[6, 13]] = -1.0  # both hands open...
        action[7 * hand] = 0.5  # ...then this one moves forward (+x)
        action[7 * hand + 6] = 1.0  # and closes
        obs = _step(humanoid_env, action, 8)
        moved = [pos - start for (pos, _), start in zip(humanoid_env.end_effector_poses(), before)]
        assert 0.6 * 8 * 0.5 * MAX_TRANSLATION < moved[hand][0] < 1.1 * 8 * 0.5 * MAX_TRANSLATION
        # The waist, shared by both arms, leans in a little and jostles the other hand by millimetres.
        assert np.abs(moved[hand][1:]).max() < 0.01 and np.linalg.norm(moved[1 - hand]) < 0.01
        openings = obs["agent_pos"][[-9, -1]]  # left, right hand's opening (0 open, -1 closed)
        assert openings[hand] < -0.7 and openings[1 - hand] > -0.05


def test_absolute_control_reaches_commanded_pose():
    env = DustEnv(task="push", robot="humanoid", obs_mode="state", control_mode="absolute")
    env.reset(seed=0)
    low, high = (np.asarray(corner) for corner in env.robot.workspace)
    targets = np.array([[0.1, 0.15, 0.15], [0.05, -0.2, 0.2]])
    action = np.zeros(ACTION_DIM, np.float32)  # zero rotation: the palms' side-grasp orientation
    for hand, target in enumerate(targets):
        action[7 * hand: 7 * hand + 3] = 2 * (target - low) / (high - low) - 1
    _step(env, action, 60)
    for (pos, rot), target in zip(env.end_effector_poses(), targets):
        assert np.linalg.norm(pos - target) < 0.01
        assert np.abs(rot - np.eye(3)).max() < 0.05


def test_ik_keeps_hands_off_the_table(humanoid_env):
    """Collision avoidance in the IK stops a hand driven straight down short of the table."""
    humanoid_env.reset(seed=0)
    down = np.zeros(ACTION_DIM)
    down[[2, 6, 13]] = -1.0  # left hand down, both hands open
    _step(humanoid_env, down, 40)
    model, data = humanoid_env.model, humanoid_env.data
    hand = mink.get_subtree_geom_ids(model, model.site("left_palm").bodyid[0])
    table = model.geom("table").id
    distances = [mujoco.mj_geomDistance(model, data, g, table, 0.1, np.zeros(6)) for g in hand
                 if model.geom_contype[g] or model.geom_conaffinity[g]]
    # Without the limit the IK drives the hand on into the table (~60 N) and the contact stops it.
    assert 0.0 < min(distances) < 0.02


def test_fast_head_frame_draws_both_hands():
    """Fast rendering draws the low-poly collision hulls: the hands are there, large enough to see."""
    env = DustEnv(task="pick_place", robot="humanoid", image_size=128)
    env.reset(seed=0)
    renderer = mujoco.Renderer(env.model, 128, 128)
    renderer.enable_segmentation_rendering()
    option = mujoco.MjvOption()
    option.geomgroup[VISUAL_GROUP], option.geomgroup[COLLISION_GROUP] = 0, 1
    renderer.update_scene(env.data, "head", option)
    ids = renderer.render()[..., 0]
    renderer.close()
    for site in ("left_palm", "right_palm"):
        hand = mink.get_subtree_geom_ids(env.model, env.model.site(site).bodyid[0])
        assert np.isin(ids, hand).sum() > 40, f"{site}: hand hardly visible in the head camera"
    env.close()
