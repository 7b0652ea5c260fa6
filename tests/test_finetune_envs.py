"""RL fine-tuning envs (noise steering, residual): SB3's env checker, the base policy recovered exactly, bad
actions named, SAC runs on them with DUST frozen; their agents play the same episodes in dust-rl eval's runner."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.env_checker import check_env

from dust_rl.agents import make_policy, save_policy
from dust_rl.agents.execution import episode_generator
from dust_rl.envs.factory import make_env
from dust_rl.evaluate.closed_loop import Episode, EvalConfig, eval_collector, eval_setup, evaluate_task
from dust_rl.rl.frozen_policy_env import FrozenPolicyEnv, observation_td
from dust_rl.rl.residual import ResidualEnv
from dust_rl.rl.steering import NoiseSteeringEnv
from dust_rl.rl.torchrl_sac import FIXED_STD_ALPHA, torchrl_env, train_sac

pytestmark = pytest.mark.usefixtures("one_thread")

IMAGE = 32


@pytest.fixture
def steering(tiny_encoder, minilm):
    env = make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE})
    policy = make_policy("dust", image_encoder=tiny_encoder, text_encoder=minilm, cameras=["front", "wrist"],
                         action_dim=7, state_dim=env.observation_space["observation.state"].shape[0],
                         horizon=4, execute_steps=2, d_model=32, n_heads=2, n_mmdit=2, n_dit=0)
    policy.set_action_bounds(env.action_space.low, env.action_space.high)
    with torch.no_grad():  # away from the zero-initialised outputs, so the noise matters
        for p in policy.trainable_parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(0)))
    wrapped = NoiseSteeringEnv(env, policy, noise_bound=2.0)
    yield wrapped, policy
    wrapped.close()


def test_sb3_accepts_the_steering_env(steering):
    env, policy = steering
    check_env(env)
    assert env.action_space.shape == (4 * 7,)
    assert env.observation_space["features"].shape == (2 * policy.config.vision_dim + policy.backbone.text_dim,)


def action_only_policy(tiny_encoder, minilm, **settings):
    """A tiny action-only policy for the steering fixture's env: no vision stream, so no vision noise."""
    torch.manual_seed(0)
    return make_policy("action_only", image_encoder=tiny_encoder, text_encoder=minilm, cameras=["front", "wrist"],
                       action_dim=7, state_dim=17, horizon=4, execute_steps=2, d_model=32, n_heads=2, n_mmdit=2,
                       n_dit=0, **settings)


def test_the_policy_own_noise_gives_its_own_chunk(tiny_encoder, minilm):
    # Exactly for a policy without a vision stream; DUST's fixed vision noise: the next test.
    policy = action_only_policy(tiny_encoder, minilm)
    env = NoiseSteeringEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE}), policy)
    obs, _ = env.reset(seed=3)
    features = env.features
    generator = episode_generator(3)
    drawn = torch.randn(1, 4, 7, generator=episode_generator(3))  # the sampler's first draw of the episode
    base = policy.plan_features(features, generator)["action_chunk"][0]
    replay = make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE})
    replay.reset(seed=3)
    steps = [replay.step(a) for a in base[:2].numpy()]  # the base policy's first two actions, run directly
    replay.close()
    obs, reward, *_ = env.step((drawn / 2.0).flatten().numpy())  # steering with the policy's own noise
    assert np.array_equal(obs["robot_state"], steps[-1][0]["observation.state"])
    assert reward == sum(float(step[1]) for step in steps)
    env.reset(seed=3)
    steered, *_ = env.step((-drawn / 2.0).flatten().numpy())
    assert not np.array_equal(steered["robot_state"], obs["robot_state"])  # other noise, other chunk
    env.close()


def test_a_steered_chunk_is_a_function_of_the_latent_alone(steering):
    env, policy = steering
    action = np.linspace(-1, 1, 28, dtype=np.float32)
    env.reset(seed=3)
    features = env.features
    chunk = env.steering.plan(policy, features, action[None])["action_chunk"]
    torch.manual_seed(123)  # other global and episode noise streams change nothing
    env.generator = episode_generator(99)
    again = env.steering.plan(policy, features, action[None], env.generator)["action_chunk"]
    assert torch.equal(chunk, again)
    # The same latent at two steps of two episodes gives one chunk; a drawn vision noise (the base policy's) would
    # give each plan its own.
    noise = env.steering.noise(action[None])
    drawn = [policy.plan_features(features, episode_generator(seed), noise)["action_chunk"] for seed in (3, 4)]
    assert not torch.equal(drawn[0], drawn[1]) and not torch.equal(drawn[0], chunk)
    env.reset(seed=3)
    first, *_ = env.step(action)
    env.reset(seed=3)
    env.generator = episode_generator(99)  # the episode's noise stream elsewhere: the env executes the same chunk
    assert np.array_equal(env.step(action)[0]["robot_state"], first["robot_state"])


def test_a_chunk_of_dense_reward_is_shaping_for_the_discount_per_chunk(steering):
    _, policy = steering
    gamma = 0.9  # per env step; per chunk of execute_steps 2: 0.81
    env = NoiseSteeringEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE,
                                                      "reward_type": "dense", "shaping_discount": gamma}),
                           policy, step_discount=gamma)
    env.reset(seed=4)
    sim = env.env.unwrapped
    before = sim.progress()
    _, reward, terminated, *_ = env.step(np.zeros(28, np.float32))
    assert not terminated  # an untrained policy does not press the button in two steps
    # float64 products and differences: a few ulps of the progress (< 1) per step
    assert abs(reward - (gamma ** 2 * sim.progress() - before)) <= 16 * np.finfo(np.float64).eps
    with pytest.raises(ValueError, match=r"step_discount must be a discount factor in \(0, 1\]"):
        NoiseSteeringEnv(env.env, policy, step_discount=1.5)
    env.close()


@pytest.mark.parametrize("finite_horizon", [False, True])
def test_a_finite_horizon_ends_at_the_time_limit_and_shows_the_time_left(steering, finite_horizon):
    _, policy = steering
    env = NoiseSteeringEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE,
                                                      "max_episode_steps": 4}), policy, finite_horizon=finite_horizon)
    check_env(env)
    obs, _ = env.reset(seed=2)
    assert ("time_left" in obs) == finite_horizon
    ends = []
    for _ in range(2):  # two chunks of execute_steps 2: the limit of 4 env steps
        obs, _, terminated, truncated, info = env.step(np.zeros(28, np.float32))
        ends.append((terminated, truncated))
        if finite_horizon:
            assert obs["time_left"][0] == 1.0 - len(env.executed) / 4
    assert not info["is_success"] and ends[0] == (False, False)
    assert ends[1] == ((True, False) if finite_horizon else (False, True))  # a failure, not a truncation
    env.close()


def test_bad_steering_actions_are_named(steering):
    env, _ = steering
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(28, np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(28,\)"):
        env.step(np.zeros(7, np.float32))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full(28, np.nan, np.float32))


def test_sac_trains_on_the_steering_env(steering):
    env, policy = steering
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    agent = SAC("MultiInputPolicy", env, learning_starts=8, batch_size=8, buffer_size=64, seed=0, device="cpu",
                policy_kwargs={"net_arch": [32, 32]})
    agent.learn(total_timesteps=16)
    assert agent.num_timesteps == 16 and agent.replay_buffer.size() == 16
    assert all(torch.equal(v, before[k]) for k, v in policy.state_dict().items())  # DUST stays frozen


@pytest.fixture
def residual(steering):
    env, policy = steering
    wrapped = ResidualEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE}), policy)
    yield wrapped, policy
    wrapped.close()


def test_zero_residual_is_the_base_policy_episode(residual):
    env, policy = residual
    check_env(env)
    obs, _ = env.reset(seed=5)
    executed = []
    for _ in range(5):  # two re-plans with execute_steps 2
        executed.append(obs["base_action"])
        obs, *_ = env.step(np.zeros(7, np.float32))
    # The same episode run directly: receding horizon, noise from the episode's generator.
    direct = make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE})
    raw, _ = direct.reset(seed=5)
    generator, expected = episode_generator(5), []
    for step in range(5):
        if step % 2 == 0:
            chunk = policy.plan(observation_td(raw), generator)["action_chunk"].numpy()
        expected.append(chunk[step % 2])
        raw, *_ = direct.step(chunk[step % 2])
    direct.close()
    assert all(np.array_equal(a, b) for a, b in zip(executed, expected, strict=True))
    assert np.array_equal(obs["robot_state"], raw["observation.state"])


def test_a_residual_moves_the_executed_action_within_bounds(residual):
    env, _ = residual
    obs, _ = env.reset(seed=5)
    low, high = env.env.action_space.low, env.env.action_space.high
    expected = np.clip(obs["base_action"] + env.residual_scale, low, high)
    stepped, *_ = env.step(np.ones(7, np.float32))
    direct = make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE})
    direct.reset(seed=5)
    raw, *_ = direct.step(expected)  # the clipped sum, executed directly
    direct.close()
    assert np.array_equal(stepped["robot_state"], raw["observation.state"])
    assert (env.residual_scale > 0).all() and not np.array_equal(expected, obs["base_action"])
    with pytest.raises(ValueError, match="residual_scale must be finite"):
        ResidualEnv(env.env, env.policy, residual_scale=-1.0)



def test_torchrl_sac_trains_on_the_steering_env(steering):
    env, policy = steering
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    logged = []
    actor = train_sac(lambda: NoiseSteeringEnv(make_env("DustFranka-v0", {"task": "press_button",
                                                                           "image_size": IMAGE}), policy),
                      steps=24, learning_starts=8, batch_size=8, net_arch=(16,), progress=False,
                      log=lambda scalars, frames: logged.append((frames, scalars)))
    assert [frames for frames, _ in logged] == list(range(8, 25))  # one update per frame once learning starts
    assert all(math.isfinite(v) for _, scalars in logged for v in scalars.values())
    td = torchrl_env(env).reset()
    assert actor(td)["action"].shape == (28,) and (actor(td)["action"].abs() <= 1).all()
    assert all(torch.equal(v, before[k]) for k, v in policy.state_dict().items())  # DUST stays frozen


def test_torchrl_sac_starts_at_the_base_policy_with_initial_std(steering):
    env, policy = steering
    td = torchrl_env(env).reset()

    def make_steering_env():
        return NoiseSteeringEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE}), policy)

    actor = train_sac(make_steering_env, steps=6, learning_starts=8, batch_size=4, net_arch=(16,), initial_std=0.1,
                      progress=False)
    out = actor(td)  # no update yet: the mean is the base policy's (noise 0), the std the one asked for
    assert torch.equal(out["loc"], torch.zeros(28)) and torch.equal(out["scale"], torch.full((28,), 0.1))
    alphas = []
    out = train_sac(make_steering_env, steps=12, learning_starts=4, batch_size=4, net_arch=(16,), initial_std=0.1,
                    progress=False, log=lambda scalars, frames: alphas.append(scalars["alpha"]))(td)
    assert len(alphas) == 9 and all(alpha == pytest.approx(FIXED_STD_ALPHA) for alpha in alphas)
    assert not torch.equal(out["loc"], torch.zeros(28))  # the updates moved the mean ...
    assert torch.equal(out["scale"], torch.full((28,), 0.1))  # ... and not the std
    with pytest.raises(ValueError, match="initial exploration std must be a finite number > 0"):
        train_sac(make_steering_env, steps=1, initial_std=float("nan"), progress=False)


def test_a_policy_with_a_read_out_shows_its_object_estimate(tiny_encoder, minilm):
    env = make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE})
    width = env.observation_space["observation.environment_state"].shape[0]
    torch.manual_seed(0)
    policy = make_policy("action_only", image_encoder=tiny_encoder, text_encoder=minilm,
                         cameras=["front", "wrist"], action_dim=7,
                         state_dim=env.observation_space["observation.state"].shape[0], horizon=4,
                         execute_steps=2, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, readout="tokens",
                         aux_state_dim=width, lambda_aux=1.0, aux_state_input=True)
    steering = NoiseSteeringEnv(env, policy)
    check_env(steering)
    obs, _ = steering.reset(seed=1)
    expected = policy.estimate_env_state(steering.features)[0]
    torch.testing.assert_close(torch.from_numpy(obs["object_estimate"]), expected, rtol=0, atol=0)
    td = torchrl_env(steering).reset()  # one flat vector, the estimate included, its entries in alphabetical order
    assert torch.equal(td["observation"], torch.cat([td["features"], td["object_estimate"], td["robot_state"]]))
    steering.close()


def test_the_residual_agent_can_see_the_future_dust_sampled_with_the_chunk(steering, tiny_encoder, minilm):
    _, policy = steering
    env = ResidualEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE}), policy,
                      world_model=True)
    check_env(env)
    obs, _ = env.reset(seed=5)
    plan = policy.plan_features(env.features, episode_generator(5))  # the same first draw as the env's plan
    expected = policy.standardised_future(plan["future_tokens"])[0].flatten()
    torch.testing.assert_close(torch.from_numpy(obs["predicted_future"]), expected, rtol=0, atol=0)
    assert np.array_equal(obs["base_action"], plan["action_chunk"][0, 0].numpy())
    td = torchrl_env(env).reset(seed=5)  # torchrl's agent sees what SB3's does: the base action and the future too
    assert torch.equal(td["observation"], torch.cat([td[name] for name in sorted(env.observation_space.spaces)]))
    assert td["observation"].shape == (sum(space.shape[0] for space in env.observation_space.spaces.values()),)
    futures = [obs["predicted_future"]]
    for _ in range(3):  # execute_steps 2: the future changes with the re-plan, not between
        obs, *_ = env.step(np.zeros(7, np.float32))
        futures.append(obs["predicted_future"])
    assert np.array_equal(futures[0], futures[1]) and not np.array_equal(futures[1], futures[2])
    assert np.array_equal(futures[2], futures[3])
    env.close()
    action_only = make_policy("action_only", image_encoder=tiny_encoder, text_encoder=minilm,
                              cameras=["front", "wrist"],
                              action_dim=7, state_dim=policy.config.state_dim, horizon=4, d_model=32,
                              n_heads=2, n_mmdit=2, n_dit=0)
    with pytest.raises(ValueError, match="world_model needs a policy that predicts the future"):
        ResidualEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE}), action_only,
                    world_model=True)


RUNNER_STEPS = 6  # three chunks of execute_steps 2


def runner_episodes(policy, tmp_path, actor, seeds: range) -> list[Episode]:
    """The episodes of ``actor`` (None: the policy itself) in dust-rl eval's runner."""
    policy.info = {"env_id": "DustFranka-v0", "env_kwargs": {"image_size": IMAGE}, "tasks": ["press_button"]}
    config = EvalConfig(policy=save_policy(policy, tmp_path / "policy.pt"), episodes=len(seeds), seed=seeds.start,
                        workers=1, videos=0, max_steps=RUNNER_STEPS, device="cpu", progress=False)
    return evaluate_task(eval_setup(config, policy), "press_button", policy, config, actor)[0]


def env_episodes(env: FrozenPolicyEnv, act, seeds: range) -> list[Episode]:
    """The episodes of the agent ``act`` stepping ``env`` itself."""
    episodes = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(act(obs))
            done = terminated or truncated
        episodes.append(Episode.of(seed, info["is_success"], torch.from_numpy(np.stack(env.executed)),
                                   torch.from_numpy(obs["robot_state"])))
    return episodes


class RecordingAgent:
    """A deterministic agent whose action depends on every entry it observes; it keeps what it saw."""

    def __init__(self, shape: tuple[int, ...]) -> None:
        self.shape, self.seen = shape, []

    def __call__(self, obs: dict) -> np.ndarray:
        self.seen.append(obs)
        entries = np.concatenate([obs[name].ravel() for name in sorted(obs)])
        return np.tanh(np.resize(entries, self.shape)).astype(np.float32)


def assert_same_views(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b) and all(x.keys() == y.keys() for x, y in zip(a, b, strict=True))
    assert all(np.array_equal(x[k], y[k]) and x[k].dtype == y[k].dtype for x, y in zip(a, b) for k in x)


@pytest.mark.parametrize("method", ["steer", "residual"])
def test_the_agent_plays_the_envs_episodes_in_the_eval_runner(steering, tmp_path, method):
    _, policy = steering
    raw = make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE, "max_episode_steps": RUNNER_STEPS})
    env = (NoiseSteeringEnv(raw, policy, finite_horizon=True) if method == "steer"
           else ResidualEnv(raw, policy, world_model=True, finite_horizon=True))
    seeds = range(7, 9)
    in_env, in_runner = RecordingAgent(env.action_space.shape), RecordingAgent(env.action_space.shape)
    expected = env_episodes(env, in_env, seeds)
    # The same agent, asked through the runner: it sees what the env showed it (the time left and, for the residual,
    # the base action and the predicted future too), and the episodes are the env's, action for action. (torchrl's
    # collector asks the policy once on the first reset before it starts, and runs on past the last seed until its
    # batch of frames is full.)
    got = runner_episodes(policy, tmp_path, env.closed_loop_actor(in_runner), seeds)
    assert "time_left" in in_env.seen[0] and len(in_env.seen) == RUNNER_STEPS // (2 if method == "steer" else 1) * 2
    probe, *played = in_runner.seen
    assert_same_views([probe, *played[:len(in_env.seen)]], in_env.seen[:1] + in_env.seen)
    assert got == expected
    base = runner_episodes(policy, tmp_path, None, seeds)  # the policy alone plays other episodes
    assert all(e.digest != b.digest for e, b in zip(got, base))
    env.close()


def test_the_runner_names_a_bad_agent_action_and_keeps_a_live_actor_in_this_process(steering, tmp_path):
    _, policy = steering
    env = NoiseSteeringEnv(make_env("DustFranka-v0", {"task": "press_button", "image_size": IMAGE}), policy)
    with pytest.raises(ValueError, match=r"the action must have shape \(28,\)"):
        runner_episodes(policy, tmp_path, env.closed_loop_actor(lambda obs: np.zeros(7, np.float32)), range(1))
    residual = ResidualEnv(env.env, policy)
    with pytest.raises(ValueError, match="NaN"):
        runner_episodes(policy, tmp_path, residual.closed_loop_actor(lambda obs: np.full(7, np.nan)), range(1))
    config = EvalConfig(policy=tmp_path / "policy.pt", workers=2, videos=0, device="cpu", progress=False)
    with pytest.raises(ValueError, match="runs in one local worker, not 2"):
        eval_collector(eval_setup(config, policy), "press_button", policy, config.worker_pool(), 0,
                       env.closed_loop_actor(lambda obs: np.zeros(28, np.float32)))
    env.close()
