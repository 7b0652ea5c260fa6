"""torchrl's own parts on the dust-rl envs and policies: multi-process collectors, batched GymEnv, image transforms."""

from __future__ import annotations

import gc

import pytest
import torch
from torchrl.collectors import MultiAsyncCollector, MultiSyncCollector
from torchrl.envs import GymEnv, InitTracker, ToTensorImage, TransformedEnv
from torchrl.envs.utils import check_env_specs

from dust_rl.agents import make_policy
from dust_rl.envs import DustEnv
from dust_rl.envs.instruction_space import decode_instruction
from dust_rl.envs.torchrl_env import make_torchrl_env

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = dict(horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=1)
CAMERAS = ["observation.image.front", "observation.image.wrist"]


def tracked_env() -> TransformedEnv:
    """A worker's env (module level, so the collectors' spawned processes can import it)."""
    return make_torchrl_env(task="press_button", image_size=32).append_transform(InitTracker())


@pytest.mark.parametrize("collector_class", [MultiSyncCollector, MultiAsyncCollector])
def test_multi_process_collectors_take_the_policys_executor(collector_class, tiny_encoder, minilm):
    """The executor crosses into the workers as it is, under torch's default file_descriptor sharing."""
    env = tracked_env()
    policy = make_policy("dust", env, image_encoder=tiny_encoder, text_encoder=minilm, execute_steps=3, **TINY)
    env.close()
    collector = collector_class([tracked_env] * 2, policy.executor(), frames_per_batch=16, total_frames=32)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
        del collector  # torchrl 0.14.1's weight-sync scheme, if collected at interpreter exit, hangs it
        gc.collect()
    assert sum(batch.numel() for batch in batches) == 32
    for batch in batches:
        assert batch["action"].shape[-1] == 7 and torch.isfinite(batch["action"]).all()
        assert set(batch["counter"].unique().tolist()) == {1, 2, 3}  # 3 actions of each chunk, then re-plan


@pytest.mark.parametrize("obs_mode", ["rgb", "state"])
def test_a_batched_gymenv_runs_with_the_strings_as_bytes(obs_mode):
    # The "dust_rl:" prefix registers the ids in the vector env's worker processes.
    env = GymEnv("dust_rl:DustFranka-v0", num_envs=2, task="press_button", image_size=32, obs_mode=obs_mode,
                 text_format="utf8")
    try:
        check_env_specs(env, seed=0)
        rollout = env.rollout(3, auto_reset=False, tensordict=env.reset(seed=0))  # sub-envs seeded 0 and 1
    finally:
        env.close()
    assert rollout.batch_size == (2, 3) and rollout["next", "is_success"].dtype == torch.bool
    assert [decode_instruction(row) for row in rollout["next", "task"][:, 0]] == ["press_button"] * 2
    single = DustEnv(task="press_button", obs_mode=obs_mode)
    expected = [single.reset(seed=seed)[1]["language_instruction"] for seed in (0, 1)]
    single.close()
    assert len(set(expected)) == 2  # a mix-up of the sub-envs shows too
    for key in ("language_instruction", ("next", "language_instruction")):  # observation in rgb mode, info in both
        assert [decode_instruction(row) for row in rollout[key][:, -1]] == expected


def test_a_policy_reads_frames_behind_to_tensor_image(tiny_encoder, minilm):
    """ToTensorImage leaves a plain GymEnv's frames channels first: the policy reads them so, not as [H, W, 3]."""
    images = TransformedEnv(GymEnv("DustFranka-v0", task="press_button", image_size=32),
                            ToTensorImage(in_keys=CAMERAS)).append_transform(InitTracker())
    canonical = make_torchrl_env(task="press_button", image_size=32)
    try:
        assert images.observation_spec[CAMERAS[0]].shape == (3, 32, 32)
        policy = make_policy("dust", images, image_encoder=tiny_encoder, text_encoder=minilm, **TINY)
        rollout = images.rollout(3, policy.executor())
        assert rollout["action"].shape == (3, 7) and images.action_spec.is_in(rollout["action"])
        with torch.no_grad():
            for p in policy.trainable_parameters():  # so that the chunk depends on the frames
                p.add_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(0)))
        images.set_seed(7)
        canonical.set_seed(7)
        plans = [policy.plan(env.reset(), torch.Generator().manual_seed(0))["action_chunk"]
                 for env in (images, canonical)]
        torch.testing.assert_close(*plans)  # the same frames, read in the same layout
    finally:
        images.close()
        canonical.close()
