"""SB3 on the image-mode env: the instruction as an embedding Box, SB3's CNN or DUST's frozen encoder on pixels."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import A2C, PPO, SAC
from stable_baselines3.common.env_checker import check_env

from dust_rl.agents import pooled_text
from dust_rl.agents.encoders.backbone import resolve_image_encoder
from dust_rl.envs.factory import make_env
from dust_rl.errors import ConfigError
from dust_rl.rl.sb3 import FrozenBackboneExtractor, SB3Observations

pytestmark = pytest.mark.usefixtures("one_thread")


def test_the_instruction_becomes_its_frozen_embedding(minilm):
    env = SB3Observations(make_env("DustFranka-v0", {"task": "press_button", "image_size": 32}), minilm)
    check_env(env)
    obs, _ = env.reset(seed=0)
    raw, _ = env.env.reset(seed=0)
    with torch.no_grad():
        tokens, mask = minilm([raw["language_instruction"]])
    np.testing.assert_array_equal(obs["language_instruction"], pooled_text(tokens, mask)[0].numpy())
    assert obs["observation/image/front"].dtype == np.uint8  # frames stay pixels for SB3's extractors
    assert "observation/environment_state" not in obs and "observation.environment_state" in raw  # no peeking
    oracle = SB3Observations(env.env, minilm, privileged=True)
    assert "observation/environment_state" in oracle.observation_space.spaces
    env.close()
    with pytest.raises(ConfigError, match=r"wraps a dust-rl env .* this env's are Box"):
        SB3Observations(gym.make("CartPole-v1"), minilm)


def test_sac_on_pixels_through_the_frozen_encoder(minilm, tiny_encoder):
    env = SB3Observations(make_env("DustFranka-v0", {"task": "press_button", "image_size": 32}), minilm)
    before = {k: v.clone() for k, v in tiny_encoder.state_dict().items()}
    agent = SAC("MultiInputPolicy", env, learning_starts=8, batch_size=8, buffer_size=64, seed=0, device="cpu",
                policy_kwargs={"features_extractor_class": FrozenBackboneExtractor, "net_arch": [16],
                               "features_extractor_kwargs": {"image_encoder": tiny_encoder}})
    agent.learn(total_timesteps=16)
    extractor = agent.policy.actor.features_extractor
    state = env.observation_space["observation/state"].shape[0]
    assert extractor.features_dim == 2 * tiny_encoder.dim + state + minilm.dim
    assert agent.num_timesteps == 16
    assert all(torch.equal(v, before[k]) for k, v in tiny_encoder.state_dict().items())  # the caller's is untouched
    assert all(torch.equal(v, before[k]) for k, v in extractor.encoder.state_dict().items())  # the actor's is frozen
    env.close()


def test_ppo_on_pixels_with_sb3s_own_cnn(minilm):
    env = SB3Observations(make_env("DustFranka-v0", {"task": "press_button", "image_size": 64}), minilm)
    agent = PPO("MultiInputPolicy", env, n_steps=8, batch_size=8, n_epochs=1, seed=0, device="cpu")
    agent.learn(total_timesteps=8)
    assert agent.num_timesteps == 8
    env.close()


@pytest.mark.parametrize("algorithm", [PPO, A2C])
@pytest.mark.parametrize("encoder", ["conv-ae", "efficientnet-lite0", "tiny"])
def test_on_policy_agents_keep_the_frozen_encoder_as_it_is(minilm, tiny_encoder, algorithm, encoder, tmp_path):
    """PPO and A2C's orthogonal init walks the extractor's modules: it must leave the pretrained encoder alone."""
    spec = tiny_encoder if encoder == "tiny" else encoder
    expected = resolve_image_encoder(spec).state_dict()
    env = SB3Observations(make_env("DustFranka-v0", {"task": "press_button", "image_size": 32}), minilm)
    batch = {"batch_size": 4} if algorithm is PPO else {}
    agent = algorithm("MultiInputPolicy", env, n_steps=4, seed=0, device="cpu", **batch,
                      policy_kwargs={"features_extractor_class": FrozenBackboneExtractor, "net_arch": [16],
                                     "features_extractor_kwargs": {"image_encoder": spec}})
    agent.learn(total_timesteps=4)
    env.close()
    extractor = agent.policy.features_extractor
    assert all(torch.equal(v, expected[k]) for k, v in extractor.encoder.state_dict().items())
    frozen = {id(p) for p in extractor.encoder.parameters()}
    assert not frozen & {id(p) for group in agent.policy.optimizer.param_groups for p in group["params"]}
    agent.save(tmp_path / "agent")
    loaded = algorithm.load(tmp_path / "agent", device="cpu").policy.features_extractor.encoder
    assert all(torch.equal(v, expected[k]) for k, v in loaded.state_dict().items())
    agent.policy.to(torch.float64)  # the encoder moves with the policy
    assert all(p.dtype == torch.float64 for p in extractor.encoder.parameters())
