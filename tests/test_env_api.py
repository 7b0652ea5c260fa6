"""The env satisfies gymnasium, torchrl and SB3 checkers and registers properly."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from torchrl.data.vla import validate_vla_tensordict
from torchrl.envs import GymEnv, SerialEnv
from torchrl.envs.libs.gym import default_info_dict_reader
from torchrl.envs.utils import check_env_specs

from dust_rl.envs import DustEnv, list_tasks
from dust_rl.envs.torchrl_env import make_torchrl_env, success_spec


def test_gymnasium_check_env_rgb(rgb_env):
    gym_check_env(rgb_env, skip_render_check=False)


def test_gymnasium_check_env_state(state_env):
    gym_check_env(state_env, skip_render_check=True)


def test_sb3_check_env_state_mode(state_env):
    sb3_check_env(state_env, warn=True, skip_render_check=True)


def test_torchrl_check_env_specs_gymenv():
    env = GymEnv("DustFranka-v0", task="pick_place", image_size=32)
    check_env_specs(env, seed=0)
    env.close()


def test_torchrl_canonical_keys():
    env = make_torchrl_env(task="pick_place", image_size=32)
    check_env_specs(env, seed=0)
    td = env.rollout(3)
    assert td["observation", "image", "front"].shape == (3, 3, 32, 32)
    assert td["observation", "state"].shape == (3, 17)
    assert "plate" in td["language_instruction"][0]
    env.close()


def test_torchrl_state_mode_has_the_same_nested_keys():
    env = make_torchrl_env(task="pick_place", obs_mode="state")
    check_env_specs(env, seed=0)
    td = env.rollout(2)
    assert td["observation", "state"].shape == (2, 17) and td["observation", "environment_state"].shape == (2, 13)
    assert set(td.keys()).isdisjoint({"agent_pos", "environment_state"})
    assert validate_vla_tensordict(td) == []  # the instruction, which state mode gives in info, included
    _, info = DustEnv(task="pick_place", obs_mode="state").reset(seed=0)
    assert env.reset(seed=0)["language_instruction"] == info["language_instruction"]
    env.close()


def test_spaces_and_observation_layout(rgb_env):
    obs, info = rgb_env.reset(seed=3)
    assert rgb_env.action_space.shape == (7,)
    assert obs["observation.image.front"].shape == (64, 64, 3)
    assert obs["observation.image.front"].dtype == np.uint8
    assert obs["observation.state"].dtype == np.float32
    assert set(info) == {"is_success", "task", "truncation_reason", "language_instruction"}
    assert obs["language_instruction"] == info["language_instruction"]
    assert info["task"] == "pick_place" and info["is_success"].dtype == bool and not info["is_success"]
    assert rgb_env.render().shape == (64, 64, 3)


def test_state_mode_renders_nothing(state_env):
    obs, _ = state_env.reset(seed=0)
    assert set(obs) == {"agent_pos", "environment_state"}
    assert state_env._renderer is None


def test_advance_then_observe_is_a_step():
    stepped, advanced = (DustEnv(task="pick_place", image_size=32) for _ in range(2))
    for env in (stepped, advanced):
        env.reset(seed=3)
    action = np.linspace(-1, 1, 7).astype(np.float32)
    obs, _, terminated, truncated, _ = stepped.step(action)
    assert advanced.advance(action) == (terminated, "")
    observed = advanced.observe()
    assert obs.keys() == observed.keys() and not truncated
    assert all(np.array_equal(obs[k], observed[k]) for k in obs if k != "language_instruction")
    assert observed["language_instruction"] == obs["language_instruction"]
    for env in (stepped, advanced):
        env.close()


def test_restore_replays_the_steps_after_a_snapshot_bit_for_bit():
    env = DustEnv(task="push", image_size=32)
    env.reset(seed=5)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (6, 7)).astype(np.float32)
    env.step(actions[0])
    snapshot = env.snapshot()

    def rollout() -> list:
        return [env.step(a)[:4] for a in actions[1:]]

    first = rollout()
    env.restore(snapshot)
    second = rollout()
    for (obs_a, *rest_a), (obs_b, *rest_b) in zip(first, second):
        assert rest_a == rest_b
        assert all(np.array_equal(obs_a[k], obs_b[k]) for k in obs_a if k != "language_instruction")
    start, end = first[0][0], first[-1][0]
    moved = [k for k in start if k != "language_instruction" and not np.array_equal(start[k], end[k])]
    assert moved  # the replayed steps were not all the same
    env.close()


def test_list_tasks_and_unknown_task():
    tasks = list_tasks("franka")
    assert "pick_place" in tasks
    with pytest.raises(ValueError, match="pick_place"):
        DustEnv(task="no_such_task")
    with pytest.raises(ValueError, match="robot"):
        list_tasks("no_such_robot")


BAD_ARGUMENTS = [
    ("task", "no_such_task"), ("task", None), ("robot", "ur5"), ("obs_mode", "depth"), ("control_mode", "joint"),
    ("image_size", 0), ("image_size", -8), ("image_size", "64"), ("image_size", True), ("image_size", 64.0),
    ("image_size", (64,)), ("image_size", (64, 0)), ("image_size", (64, "64")), ("image_size", (32, 32, 3)),
    ("image_size", 100000), ("image_size", (32, 1025)),
    ("cameras", []), ("cameras", "front"), ("cameras", ["front", "front"]), ("cameras", ["front", "nope"]),
    ("reward_type", "shaped"), ("render_mode", "human"), ("render_quality", "ultra"),
    ("max_episode_steps", 0), ("max_episode_steps", -5), ("max_episode_steps", 10.5), ("max_episode_steps", True),
    ("control_hz", -20.0), ("control_hz", 0), ("control_hz", float("nan")), ("control_hz", float("inf")),
    ("control_hz", "20"), ("control_hz", True), ("physics_dt", 0.0), ("physics_dt", -0.002),
    ("physics_dt", float("nan")), ("physics_dt", 0.1), ("physics_dt", 0.003), ("ik_solver", "no_such_solver"),
    ("privileged_state", "false"), ("privileged_state", 1),
]


@pytest.mark.parametrize("name, value", BAD_ARGUMENTS, ids=[f"{n}={v!r}" for n, v in BAD_ARGUMENTS])
def test_bad_constructor_arguments_name_the_argument_and_value(name, value):
    with pytest.raises(ValueError) as raised:
        DustEnv(**{"task": "pick_place", name: value})
    message = str(raised.value)
    assert name in message and repr(value) in message


def test_valid_constructor_arguments_are_taken_as_given():
    env = DustEnv(task="pick_place", image_size=(np.int64(24), 40), cameras=["wrist"], max_episode_steps=2,
                  control_hz=10, physics_dt=0.004, ik_solver="quadprog")
    obs, _ = env.reset(seed=0)
    assert obs["observation.image.wrist"].shape == (24, 40, 3) and "observation.image.front" not in obs
    assert env.n_substeps == 25 and env.control_dt == pytest.approx(0.1) and env.metadata["render_fps"] == 10
    assert not env.step(np.zeros(7, np.float32))[3] and env.step(np.zeros(7, np.float32))[3]  # 2-step time limit
    env.close()


@pytest.mark.parametrize("robot, task", [("franka", "pick_place"), ("humanoid", "push")])
def test_privileged_state_appends_the_objects_to_the_robot_state(robot, task):
    plain, oracle = (DustEnv(task=task, robot=robot, obs_mode="state", privileged_state=flag) for flag in (False, True))
    obs, _ = plain.reset(seed=3)
    seen, _ = oracle.reset(seed=3)
    assert oracle.observation_space["agent_pos"].shape == seen["agent_pos"].shape
    np.testing.assert_array_equal(seen["agent_pos"], np.concatenate([obs["agent_pos"], obs["environment_state"]]))
    gym_check_env(oracle, skip_render_check=True)
    plain.close()
    oracle.close()


def test_privileged_noise_misplaces_each_object_by_one_offset_per_episode():
    env = DustEnv(task="pick_place", obs_mode="state", privileged_state=True, privileged_noise=0.03)
    offsets = []
    for seed in (0, 0, 1):
        obs, _ = env.reset(seed=seed)
        seen = [obs["agent_pos"][-obs["environment_state"].size:] - obs["environment_state"]]
        for _ in range(3):
            obs, *_ = env.step(np.zeros(7, np.float32))
            seen.append(obs["agent_pos"][-obs["environment_state"].size:] - obs["environment_state"])
        assert all(np.allclose(s, seen[0], atol=1e-6) for s in seen)  # the same offset all episode (float32 sums)
        offsets.append(seen[0])
    assert np.allclose(offsets[0], offsets[1], atol=1e-6) and not np.allclose(offsets[0], offsets[2], atol=1e-3)
    assert 0 < np.abs(offsets[0]).max() < 0.03 * 6
    env.close()
    with pytest.raises(ValueError, match="privileged_noise needs privileged_state"):
        DustEnv(task="pick_place", obs_mode="state", privileged_noise=0.01)
    with pytest.raises(ValueError, match="privileged_noise must be a finite number >= 0"):
        DustEnv(task="pick_place", obs_mode="state", privileged_state=True, privileged_noise=-1.0)


def test_make_without_import_uses_module_prefix():
    code = ("import gymnasium as gym; env = gym.make('dust_rl:DustFranka-v0', task='pick_place', obs_mode='state');"
            "_, info = env.reset(seed=0); print(info['language_instruction'])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "plate" in out.stdout


def test_make_vec_async():
    envs = gym.make_vec("DustFranka-v0", num_envs=2, vectorization_mode="async",
                        task="pick_place", obs_mode="state")
    obs, _ = envs.reset(seed=[0, 1])
    obs, reward, terminated, truncated, info = envs.step(np.zeros((2, 7), np.float32))
    assert obs["agent_pos"].shape == (2, 17)
    assert reward.shape == (2,) and info["task"].tolist() == ["pick_place", "pick_place"]
    envs.close()


@pytest.mark.parametrize("mode,vector_kwargs", [("sync", {}), ("async", {}), ("async", {"copy": False})])
def test_every_vector_mode_returns_the_real_instruction_in_rgb_mode(mode, vector_kwargs):
    seeds = [3, 4]
    expected = []
    for seed in seeds:
        single = DustEnv(task="press_button", image_size=32)
        expected.append(single.reset(seed=seed)[1]["language_instruction"])
        single.close()
    assert len(set(expected)) == 2  # two different instructions, so a mix-up shows too
    envs = gym.make_vec("DustFranka-v0", num_envs=2, vectorization_mode=mode, vector_kwargs=vector_kwargs,
                        task="press_button", image_size=32)
    obs, info = envs.reset(seed=seeds)
    assert list(obs["language_instruction"]) == expected == list(info["language_instruction"])
    obs, *_ = envs.step(np.zeros((2, 7), np.float32))
    assert list(obs["language_instruction"]) == expected
    assert obs["observation.image.front"].shape == (2, 32, 32, 3)
    envs.close()


def success_reading_env() -> GymEnv:
    env = GymEnv("DustFranka-v0", task="press_button", obs_mode="state")
    return env.set_info_dict_reader(default_info_dict_reader(["is_success"], spec=[success_spec()]))


def test_torchrls_info_reader_reads_is_success_as_a_bool():
    env = success_reading_env()
    check_env_specs(env, seed=0)
    rollout = env.rollout(3)
    assert rollout["next", "is_success"].shape == (3,)
    assert rollout["next", "is_success"].dtype == torch.bool and not rollout["next", "is_success"].any()
    env.close()
    serial = SerialEnv(1, success_reading_env)
    assert serial.rollout(2)["next", "is_success"].dtype == torch.bool  # its buffers follow the spec
    serial.close()


def test_a_vector_envs_success_flags_are_bools():
    envs = gym.make_vec("DustFranka-v0", num_envs=2, vectorization_mode="sync", task="press_button", obs_mode="state")
    _, info = envs.reset(seed=0)
    assert info["is_success"].dtype == bool
    _, _, _, _, info = envs.step(np.zeros((2, 7), np.float32))
    assert info["is_success"].dtype == bool and not info["is_success"].any()
    envs.close()


def test_absolute_control_reaches_commanded_pose():
    env = DustEnv(task="pick_place", obs_mode="state", control_mode="absolute")
    env.reset(seed=0)
    target = np.array([0.5, 0.1, 0.25])
    low, high = (np.asarray(corner) for corner in env.robot.workspace)
    action = np.zeros(7, np.float32)
    action[:3] = 2 * (target - low) / (high - low) - 1
    action[3] = 1.0  # axis-angle (pi, 0, 0): gripper pointing down
    for _ in range(60):
        env.step(action)
    assert np.linalg.norm(env.end_effector_pose()[0] - target) < 0.01


def test_object_state_gives_square_objects_yaws_that_their_quarter_turns_share():
    import mujoco

    from dust_rl.envs.tasks.base import set_free_body_pose

    env = DustEnv(task="stack", obs_mode="state")
    env.reset(seed=0)
    sim = env.unwrapped

    def top_cube_yaw(yaw: float) -> np.ndarray:  # the top cube's (sin, cos) after the three positions
        set_free_body_pose(sim.data, "top_cube", sim.data.body("top_cube").xpos.copy(), yaw)
        mujoco.mj_forward(sim.model, sim.data)
        return sim.observe()["environment_state"][9:11].astype(np.float64)

    base = top_cube_yaw(0.1)
    tolerance = 8 * np.finfo(np.float32).eps  # float32 state of a float64 sine
    np.testing.assert_allclose(top_cube_yaw(0.1 + np.pi / 2), base, atol=tolerance)  # a quarter turn: the same
    np.testing.assert_allclose(top_cube_yaw(0.1 - np.pi / 2), base, atol=tolerance)
    np.testing.assert_allclose(top_cube_yaw(0.1 + np.pi / 4), -base, atol=tolerance)  # an eighth: opposite
    np.testing.assert_allclose(base, [np.sin(0.4), np.cos(0.4)], atol=tolerance)
    env.close()
