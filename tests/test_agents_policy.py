"""torchrl policy: make_policy variants, sampler options, checkpoints, receding horizon in a Collector."""

from __future__ import annotations

import pytest
import torch
from tensordict import NonTensorData, NonTensorStack, TensorDict
from torchrl.collectors import Collector
from torchrl.envs import GymEnv, InitTracker, TransformedEnv

from dust_rl.agents import (
    VARIANTS,
    DustPolicy,
    SamplerConfig,
    env_spec,
    load_policy,
    make_policy,
    save_policy,
)
from dust_rl.agents.factory import POLICY_KIND
from dust_rl.envs.torchrl_env import make_torchrl_env
from dust_rl.errors import CheckpointError, UserError
from dust_rl.keys import ACTION_NOISE_KEY, PREDICTED_FUTURE_KEY
from dust_rl.storage.checkpoint_files import load_checkpoint, save_checkpoint

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = dict(horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=1)
CAMERAS = ["front", "wrist"]


def observation(batch: tuple[int, ...] = (2,), state_dim: int = 5, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    n = int(torch.tensor(batch).prod())
    texts = ["press the red button", "open the drawer"] * n
    images = {cam: torch.randint(0, 256, (*batch, 3, 32, 32), dtype=torch.uint8, generator=g) for cam in CAMERAS}
    td = TensorDict({"observation": {"image": images, "state": torch.randn(*batch, state_dim, generator=g)}},
                    batch_size=batch)
    if len(batch) == 1:
        td["language_instruction"] = NonTensorStack.from_list(texts[:n])
    else:  # one instruction for the whole batch
        td["language_instruction"] = NonTensorData(texts[0], batch_size=batch)
    return td


def tiny_policy(variant: str, encoder, text, **overrides) -> DustPolicy:
    sizes = {**TINY, "action_dim": 3, "state_dim": 5, **overrides}
    return make_policy(variant, image_encoder=encoder, text_encoder=text, cameras=CAMERAS, **sizes)


def perturb(policy: DustPolicy) -> None:
    """Move every trainable weight away from its initialisation (zero-initialised outputs ignore the inputs)."""
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in policy.trainable_parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_variant_writes_a_chunk_and_an_action(variant, tiny_encoder, minilm):
    policy = tiny_policy(variant, tiny_encoder, minilm)
    assert isinstance(policy, DustPolicy) and policy.config.variant == variant
    assert policy.in_keys[:2] == [("observation", "image", "front"), ("observation", "image", "wrist")]
    for batch in [(2,), (), (2, 3)]:
        torch.manual_seed(0)
        out = policy(observation(batch))
        assert out["vla_action", "chunk"].shape == (*batch, 6, 3)
        torch.testing.assert_close(out["action"], out["vla_action", "chunk"][..., 0, :])
        # The future sampled with the chunk comes out too (the same joint sample as plan's).
        assert (PREDICTED_FUTURE_KEY in policy.out_keys) == (variant != "action_only")
        if variant != "action_only":
            torch.manual_seed(0)
            planned = policy.plan(observation(batch))
            assert torch.equal(out[PREDICTED_FUTURE_KEY], planned["future_tokens"])
            assert torch.equal(out["vla_action", "chunk"], planned["action_chunk"])


@pytest.mark.parametrize("variant", ["dust", "action_only"])
def test_the_initial_action_noise_steers_the_chunk(variant, tiny_encoder, minilm):
    policy = tiny_policy(variant, tiny_encoder, minilm)
    perturb(policy)
    obs = observation((2,))
    shape = (2, policy.config.horizon, policy.config.action_dim)
    drawn = torch.randn(shape, generator=torch.Generator().manual_seed(3))  # what the sampler draws first
    base = policy.plan(obs, torch.Generator().manual_seed(3))
    same = policy.plan(obs, torch.Generator().manual_seed(3), action_noise=drawn)
    assert all(torch.equal(base[k], same[k]) for k in base.keys())  # passing the drawn noise changes nothing
    steered = policy.plan(obs, torch.Generator().manual_seed(3), action_noise=-drawn)
    assert not torch.equal(steered["action_chunk"], base["action_chunk"])
    if variant == "action_only":  # no vision noise: the chunk is a function of the action noise alone
        again = policy.plan(obs, torch.Generator().manual_seed(4), action_noise=-drawn)
        assert torch.equal(again["action_chunk"], steered["action_chunk"])
    torch.manual_seed(0)
    through_forward = policy(obs.clone().set(ACTION_NOISE_KEY, -drawn))
    torch.manual_seed(0)
    assert torch.equal(through_forward["vla_action", "chunk"], policy.plan(obs, action_noise=-drawn)["action_chunk"])
    with pytest.raises(ValueError, match=r"action_noise must have shape \(2, 6, 3\)"):
        policy.plan(obs, action_noise=torch.zeros(2, 5, 3))


def test_normalisation_and_bounds_map_chunks_to_env_units(tiny_encoder, minilm):
    stats = {"state": {"mean": [0.0] * 5, "std": [1.0] * 5}, "action": {"mean": [10.0, 0, 0], "std": [0.0, 1, 1]}}
    policy = tiny_policy("dust", tiny_encoder, minilm, stats=stats)
    chunk = policy(observation())["vla_action", "chunk"]
    assert torch.all((chunk[..., 0] - 10).abs() < 0.1)  # std 0 is floored, so dim 0 sits at its mean
    policy.set_action_bounds(torch.tensor([-1.0, -0.5, -0.5]), torch.tensor([1.0, 0.5, 0.5]))
    chunk = policy(observation())["vla_action", "chunk"]
    assert torch.all(chunk[..., 0] == 1.0) and chunk.abs().max() <= 1.0


@pytest.mark.parametrize("sampler,n_action_steps,ratio,evaluations", [
    ("async", 2, 4, 8), ("sync", 3, 1, 3), ("action_only", 4, 1, 4)])
def test_sampler_options(sampler, n_action_steps, ratio, evaluations, tiny_encoder, minilm):
    policy = tiny_policy("dust", tiny_encoder, minilm)
    policy.set_sampler(SamplerConfig(sampler, n_action_steps, ratio))
    calls = []
    policy.model.register_forward_hook(lambda *args: calls.append(1))
    policy(observation())
    assert len(calls) == evaluations and policy.config.sampler == sampler
    joint = tiny_policy("joint", tiny_encoder, minilm)
    if sampler != "sync":
        with pytest.raises(ValueError, match="shares one timestep"):
            joint.set_sampler(SamplerConfig(sampler, n_action_steps, ratio))


def test_checkpoint_round_trip_gives_identical_outputs(tiny_encoder, minilm, tmp_path):
    policy = tiny_policy("dust", tiny_encoder, minilm, execute_steps=3)
    perturb(policy)
    with torch.no_grad():
        policy.normalizer.set_stats({"state": {"mean": [1.0] * 5, "std": [2.0] * 5},
                                    "action": {"mean": [0.5, 0, 0], "std": [3.0, 1, 1]}})
    policy.set_sampler(SamplerConfig("async", 2, 2))
    policy.info = {"env_id": "DustFranka-v0", "tasks": ["pick_place"]}
    path = save_policy(policy, tmp_path / "policy.pt")
    loaded = load_policy(path)
    assert loaded.execute_steps == loaded.executor().replan_interval == 3 and loaded.config == policy.config
    assert loaded.info == policy.info
    obs = observation()
    expected = policy.plan(obs, torch.Generator().manual_seed(0))
    got = loaded.plan(obs, torch.Generator().manual_seed(0))
    assert torch.equal(got["action_chunk"], expected["action_chunk"])
    assert torch.equal(got["future_tokens"], expected["future_tokens"])
    assert not list(tmp_path.glob(".*.tmp"))


def test_policy_files_naming_the_old_agent_layer_still_load(tiny_encoder, minilm, tmp_path):
    policy = tiny_policy("dust", tiny_encoder, minilm)
    perturb(policy)
    payload = load_checkpoint(save_policy(policy, tmp_path / "new.pt"), POLICY_KIND)
    payload["state_dict"] = {k.replace("model.", "agent.model.", 1) if k.startswith("model.") else k: v
                             for k, v in payload["state_dict"].items()}  # as files written before the change
    assert any(k.startswith("agent.model.") for k in payload["state_dict"])
    old = load_policy(save_checkpoint(payload, tmp_path / "old.pt", POLICY_KIND))
    obs = observation()
    expected = policy.plan(obs, torch.Generator().manual_seed(0))["action_chunk"]
    assert torch.equal(old.plan(obs, torch.Generator().manual_seed(0))["action_chunk"], expected)


def test_policy_files_from_before_world_model_selection_was_retired_load_at_its_values_only(tiny_encoder, minilm,
                                                                                            tmp_path):
    payload = load_checkpoint(save_policy(tiny_policy("dust", tiny_encoder, minilm), tmp_path / "new.pt"), POLICY_KIND)
    before = {**payload["config"], "scorer_hidden": 0, "candidates": 1}  # every policy file of before holds them
    assert load_policy(save_checkpoint({**payload, "config": before}, tmp_path / "old.pt", POLICY_KIND))
    for name, value in (("scorer_hidden", 128), ("candidates", 4)):  # what dust-rl finetune wm-select wrote
        save_checkpoint({**payload, "config": {**before, name: value}}, tmp_path / "selected.pt", POLICY_KIND)
        with pytest.raises(CheckpointError, match=rf"{name} = {value}: a setting this version removed .* 74cb2e1"):
            load_policy(tmp_path / "selected.pt")


def test_loading_a_corrupt_or_mismatched_checkpoint_fails_clearly(tiny_encoder, minilm, tmp_path):
    path = save_policy(tiny_policy("dust", tiny_encoder, minilm, state_dim=17), tmp_path / "policy.pt")
    (tmp_path / "cut.pt").write_bytes(path.read_bytes()[:1000])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_policy(tmp_path / "cut.pt")
    env = make_torchrl_env(task="press_button", image_size=32)
    try:
        with pytest.raises(CheckpointError, match="action_dim: policy has 3, env has 7"):
            load_policy(path, env)
    finally:
        env.close()
    payload = torch.load(path, weights_only=True)
    payload["config"]["d_model"] = 64  # weights no longer fit the config
    torch.save(payload, tmp_path / "edited.pt")
    with pytest.raises(CheckpointError, match="does not load"):
        load_policy(tmp_path / "edited.pt")


def test_receding_horizon_in_a_collector(tiny_encoder, minilm):
    env = make_torchrl_env(task="press_button", image_size=32)
    env.append_transform(InitTracker())
    try:
        policy = make_policy("dust", env, image_encoder=tiny_encoder, text_encoder=minilm, execute_steps=4,
                             **{**TINY, "horizon": 8})
        assert policy.config.action_dim == 7 and policy.config.state_dim == 17 and policy.cameras == CAMERAS
        plans = []
        policy.register_forward_hook(lambda *args: plans.append(1))
        plans.clear()
        collector = Collector(env, policy.executor(), frames_per_batch=10, total_frames=10)
        try:
            batch = next(iter(collector))
        finally:
            collector.shutdown()
    finally:
        env.close()
    assert batch["action"].shape == (10, 7)
    low, high = env.action_spec.space.low, env.action_spec.space.high
    assert torch.all(batch["action"] >= low) and torch.all(batch["action"] <= high)
    counter = batch["counter"].squeeze(-1).tolist()
    assert counter == [1, 2, 3, 4, 1, 2, 3, 4, 1, 2]  # 4 actions of each 8-step chunk, then re-plan
    # Each executed action is the chunk entry its counter points at.
    chunk = batch["vla_action", "chunk"]
    torch.testing.assert_close(batch["action"], chunk[torch.arange(10), batch["counter"].squeeze(-1) - 1])
    # Every step carries the future predicted at its latest re-plan, refreshed with the chunk.
    future = batch[PREDICTED_FUTURE_KEY]
    assert future.shape == (10, policy.config.n_vision_tokens, policy.config.vision_dim)
    assert all(torch.equal(future[i], future[i - 1]) == (counter[i] != 1) for i in range(1, 10))
    assert len(plans) <= 4  # 3 chunks for 10 steps (+ the collector's spec probe)


def test_an_env_without_init_tracker_is_told_to_append_it(tiny_encoder, minilm):
    env = GymEnv("DustFranka-v0", task="press_button", image_size=32)
    try:
        policy = make_policy("dust", env=env, image_encoder=tiny_encoder, text_encoder=minilm, **TINY)
        with pytest.raises(UserError, match=r"no 'is_init' entry.*TransformedEnv\(env, InitTracker\(\)\)$") as error:
            env.rollout(3, policy.executor())
        assert "\n" not in str(error.value)
        assert TransformedEnv(env, InitTracker()).rollout(3, policy.executor())["action"].shape == (3, 7)
    finally:
        env.close()


def test_a_plain_gym_env_works_as_is(tiny_encoder, minilm):
    """make_policy and the policy read a plain GymEnv's flat keys exactly as the canonical ones."""
    flat = TransformedEnv(GymEnv("DustFranka-v0", task="press_button", image_size=32), InitTracker())
    canonical = make_torchrl_env(task="press_button", image_size=32)
    try:
        policy = make_policy("dust", flat, image_encoder=tiny_encoder, text_encoder=minilm, **TINY)
        assert policy.config.action_dim == 7 and policy.config.state_dim == 17 and policy.cameras == CAMERAS
        assert torch.equal(policy.action_low, torch.as_tensor(env_spec(canonical)["action_low"]))
        rollout = flat.rollout(3, policy.executor())
        assert rollout["action"].shape == (3, 7) and flat.action_spec.is_in(rollout["action"])
        # One observation seen through both key layouts gives the same chunk (images are not transposed).
        perturb(policy)
        flat.set_seed(7)
        canonical.set_seed(7)
        plans = [policy.plan(env.reset(), torch.Generator().manual_seed(0))["action_chunk"]
                 for env in (flat, canonical)]
        assert torch.equal(*plans)
    finally:
        flat.close()
        canonical.close()


def test_an_env_without_robot_state_gets_a_clear_error(tiny_encoder, minilm):
    env = GymEnv("Pendulum-v1")
    try:
        with pytest.raises(ValueError, match="make_torchrl_env"):
            make_policy("dust", env, image_encoder=tiny_encoder, text_encoder=minilm, **TINY)
    finally:
        env.close()
