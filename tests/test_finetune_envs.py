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
from dust_rl.evaluate.closed_loop import EvalConfig, eval_collector, eval_setup, evaluate_task
from dust_rl.evaluate.records import Episode
from dust_rl.rl.asymmetric import AsymmetricSACPolicy
from dust_rl.rl.critic_limits import LayerNormReLU
from dust_rl.rl.frozen_policy_env import FrozenPolicyEnv, observation_td
from dust_rl.rl.residual import ResidualEnv
from dust_rl.rl.start_at_base import BaseWarmupSAC
from dust_rl.rl.steering import NoiseSteeringEnv, latent_map, prior_latents
from dust_rl.rl.torchrl_sac import FIXED_STD_ALPHA, sac_critic, torchrl_env, train_sac
from dust_rl.rl.vector import GymSteeringVectorEnv, SB3SteeringVecEnv
from dust_rl.runtime.settings import RuntimeSettings

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
    state = env.generator.get_state()
    again = env.steering.plan(policy, features, action[None], env.generator)["action_chunk"]
    assert torch.equal(chunk, again) and torch.equal(env.generator.get_state(), state)  # nothing drawn
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
    policy.info = {"env_id": "DustFranka-v0", "env_kwargs": {"image_size": IMAGE}, "tasks": ["press_button"],
                   "image_size": [IMAGE, IMAGE]}
    config = EvalConfig(policy=save_policy(policy, tmp_path / "policy.pt"), episodes=len(seeds), seed=seeds.start,
                        workers=1, videos=0, max_steps=RUNNER_STEPS,
                        runtime=RuntimeSettings(device="cpu", progress=False))
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
    config = EvalConfig(policy=tmp_path / "policy.pt", workers=2, videos=0,
                        runtime=RuntimeSettings(device="cpu", progress=False))
    with pytest.raises(ValueError, match="runs in one local worker, not 2"):
        eval_collector(eval_setup(config, policy), "press_button", policy, config.worker_pool(), 0,
                       env.closed_loop_actor(lambda obs: np.zeros(28, np.float32)))
    env.close()


# -- DSRL's design: latent actions, rendering at chunk ends, N envs per plan call, an asymmetric critic, the -1
#    per-step reward and the base policy's own warm-up.

def steering_env(policy, max_steps: int | None = None, **settings) -> NoiseSteeringEnv:
    """A fresh press_button steering env of ``policy``."""
    kwargs = {"task": "press_button", "image_size": IMAGE} | ({"max_episode_steps": max_steps} if max_steps else {})
    return NoiseSteeringEnv(make_env("DustFranka-v0", kwargs), policy, **settings)


def counted(monkeypatch, owner: object, name: str) -> list[int]:
    """Count the calls of ``owner.name`` (the real one runs); the list grows by one per call."""
    calls, method = [], getattr(owner, name)

    def wrapper(*args, **kwargs):
        calls.append(1)
        return method(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapper)
    return calls


def test_a_latent_maps_to_the_noise_of_the_whole_chunk(steering):
    _, policy = steering
    repeat = latent_map(7, (4, 7))  # one row of Da repeated over H
    latent = np.linspace(-1, 1, 7, dtype=np.float32)
    env = steering_env(policy, latent_dim=7, noise_bound=1.5)
    check_env(env)
    assert env.action_space.shape == (7,) and torch.equal(repeat, env.steering.latent_map)
    noise = env.steering.noise(latent[None])
    assert noise.shape == (1, 4, 7) and all(torch.equal(row, torch.from_numpy(latent * 1.5)) for row in noise[0])
    other = latent_map(5, (4, 7))  # a fixed random map, the same in every process
    assert other.shape == (28, 5) and torch.equal(other, latent_map(5, (4, 7)))
    assert latent_map(None, (4, 7)) is None and latent_map(28, (4, 7)) is None  # the noise itself
    env.reset(seed=1)
    obs, *_ = env.step(latent)
    assert np.isfinite(obs["robot_state"]).all()
    with pytest.raises(ValueError, match=r"latent_dim must be in \[1, 28\]"):
        latent_map(29, (4, 7))
    # Latents from N(0, I) give noise entries of variance about 1: the policy's own noise, entry by entry.
    torch.manual_seed(0)
    drawn = prior_latents(4000, 5, noise_bound=4.0)
    assert drawn.shape == (4000, 5) and drawn.abs().max() <= 1
    assert 0.9 < float((drawn * 4.0 @ other.T).std()) < 1.1
    env.close()


def test_a_steering_step_renders_once_after_its_chunk(steering, monkeypatch):
    env, _ = steering
    env.reset(seed=2)
    renders = counted(monkeypatch, env.env.unwrapped, "_render_camera")
    env.step(np.zeros(28, np.float32))  # execute_steps 2: two control steps, one observation of two cameras
    assert len(env.executed) == 2 and len(renders) == 2


def test_n_envs_step_as_each_alone_with_one_plan_and_one_encoder_call(steering, monkeypatch):
    _, policy = steering
    settings = {"max_steps": 4, "finite_horizon": True, "reward_penalty": True, "latent_dim": 7}
    alone = [steering_env(policy, **settings) for _ in range(2)]
    together = SB3SteeringVecEnv([steering_env(policy, **settings) for _ in range(2)])
    together.seed(5)
    obs = together.reset()
    for i, env in enumerate(alone):  # env i seeded seed + i, as SB3 does
        for name, value in env.reset(seed=5 + i)[0].items():
            torch.testing.assert_close(torch.from_numpy(obs[name][i]), torch.from_numpy(value))
    plans, encodings = counted(monkeypatch, policy, "plan_features"), counted(monkeypatch, policy,
                                                                              "observation_features")
    actions = np.stack([np.full(7, 0.5, np.float32), np.full(7, -0.5, np.float32)])
    calls = []
    for _ in range(2):  # two chunks of 2: the time limit of 4, then a reset
        before = len(plans), len(encodings)
        obs, rewards, dones, infos = together.step(actions)
        calls.append((len(plans) - before[0], len(encodings) - before[1]))
        results = [env.step(action) for env, action in zip(alone, actions)]
        assert list(rewards) == [r[1] for r in results] == [-1.0, -1.0]  # -1 per RL step until success
        seen = [info["terminal_observation"] if done else {k: v[i] for k, v in obs.items()}
                for i, (info, done) in enumerate(zip(infos, dones))]
        for got, (want, *_) in zip(seen, results):
            for name in want:
                torch.testing.assert_close(torch.from_numpy(got[name]), torch.from_numpy(want[name]))
    assert calls == [(1, 1), (1, 2)]  # one plan and one encoder call per step, one more for the resets
    assert dones.all() and not any(info["TimeLimit.truncated"] for info in infos)  # finite horizon: terminated
    assert [info["episode"] for info in infos][0]["r"] == -2.0 and infos[0]["episode"]["l"] == 2
    assert obs["time_left"].tolist() == [[1.0], [1.0]]  # the reset observations, time left anew
    assert together.env_steps == 8
    together.env_steps = 100  # a resumed run's count carries on
    together.step(actions)
    assert together.env_steps == 104
    agent = SAC("MultiInputPolicy", together, learning_starts=4, batch_size=4, buffer_size=16, seed=0, device="cpu",
                gradient_steps=2, policy_kwargs={"net_arch": [16]})
    agent.learn(total_timesteps=8)  # 4 RL steps of 2 envs
    assert agent.num_timesteps == 8 and agent.replay_buffer.pos == 4 and agent._n_updates == 2 * 2
    together.close()


def test_the_critic_reads_the_object_state_the_actor_never_sees(steering):
    _, policy = steering
    env = steering_env(policy, object_state=True)
    check_env(env)
    obs, _ = env.reset(seed=4)
    assert np.array_equal(obs["object_state"], env.env.unwrapped.observe()["observation.environment_state"])
    agent = SAC(AsymmetricSACPolicy, env, seed=0, device="cpu", policy_kwargs={"net_arch": [16]})
    moved = {**obs, "object_state": obs["object_state"] + 1.0}
    acted = [agent.predict(o, deterministic=True)[0] for o in (obs, moved)]
    seen = {k: v for k, v in obs.items() if k != "object_state"}  # the closed-loop actor's view
    assert np.array_equal(acted[0], acted[1]) and np.array_equal(agent.predict(seen, deterministic=True)[0], acted[0])
    q = [agent.critic(agent.policy.obs_to_tensor(o)[0], torch.zeros(1, 28))[0].item() for o in (obs, moved)]
    assert q[0] != q[1]
    assert "object_state" not in env.view.actor_view.space.spaces
    with pytest.raises(ValueError, match="features extractors of its own"):
        SAC(AsymmetricSACPolicy, env, device="cpu", policy_kwargs={"share_features_extractor": True})
    wrapped = torchrl_env(env)  # torchrl: the actor's vector leaves it out, the critic reads it beside
    td = wrapped.reset(seed=4).set("action", torch.zeros(28))
    assert td["observation"].shape == (sum(env.observation_space[k].shape[0] for k in seen),)
    critic = sac_critic(wrapped, (16,))
    q = [critic(td.clone().set("object_state", td["object_state"] + shift))["state_action_value"]
         for shift in (0.0, 1.0)]
    assert critic.in_keys == ["observation", "object_state", "action"] and not torch.equal(*q)
    env.close()


def test_the_features_can_leave_the_instruction_out(steering):
    env, policy = steering
    without = steering_env(policy, instruction=False)
    full, _ = env.reset(seed=1)
    short, _ = without.reset(seed=1)
    images = 2 * policy.config.vision_dim
    assert short["features"].shape == (images,) and np.array_equal(short["features"], full["features"][:images])
    without.close()


def test_a_penalty_pays_minus_one_per_step_and_nothing_on_success(steering):
    _, policy = steering
    env = steering_env(policy, max_steps=4, finite_horizon=True, reward_penalty=True)
    env.reset(seed=0)
    assert env.step(np.zeros(28, np.float32))[1] == -1.0
    assert env.rl_reward(1.0, {"is_success": np.bool_(True)}) == 0.0  # the succeeding step
    assert env.rl_reward(0.0, {"is_success": np.bool_(False)}) == -1.0
    assert steering_env(policy).rl_reward(0.5, {"is_success": np.bool_(False)}) == 0.5  # else the env's own
    env.close()


def test_the_warm_up_acts_with_the_base_policy_own_latents(steering):
    _, policy = steering
    env = steering_env(policy, noise_bound=4.0)
    agent = BaseWarmupSAC("MultiInputPolicy", env, learning_starts=8, batch_size=4, buffer_size=16, seed=0,
                          device="cpu", policy_kwargs={"net_arch": [16]})
    agent.noise_bound = 4.0
    agent.learn(total_timesteps=8)
    warm_up = agent.replay_buffer.actions[:8]
    # N(0, 1) latents scaled to the bound of 4: a spread of 1/4, where SB3's uniform warm-up has 0.58.
    assert agent._n_updates == 0 and 0.15 < warm_up.std() < 0.35
    logged = []
    actor = train_sac(lambda: GymSteeringVectorEnv([steering_env(policy, noise_bound=4.0) for _ in range(2)]),
                      steps=12, learning_starts=8, batch_size=4, net_arch=(16,), layer_norm=True, updates_per_step=3,
                      base_warmup=True, progress=False, log=lambda scalars, frames: logged.append(frames))
    assert logged == [8] * 3 + [10] * 3 + [12] * 3  # 3 updates after each step of both envs once learning starts
    assert isinstance(actor.module[0].module[0][1], LayerNormReLU)
    with pytest.raises(ValueError, match="pick one"):
        train_sac(lambda: env, steps=2, initial_std=0.1, base_warmup=True, progress=False)
    env.close()


def test_torchrl_resets_the_finished_envs_of_a_vector(steering):
    _, policy = steering
    vector = GymSteeringVectorEnv([steering_env(policy, max_steps=2 * (i + 1)) for i in range(2)])
    env = torchrl_env(vector)
    env.set_seed(0)
    rollout = env.rollout(4, break_when_any_done=False)  # env 0 ends every chunk, env 1 every second
    assert rollout["next", "done"].squeeze(-1).tolist() == [[True, True, True, True], [False, True, False, True]]
    assert [env.env_steps for env in vector.envs] == [4 * 2, 4 * 2]
    env.close()
