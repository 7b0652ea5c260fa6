"""The read-out warm-up: it fits the read-out (tokens or pixel keypoints), touches nothing else, then freezes it."""

from __future__ import annotations

import pytest
import torch

from dust_rl.agents import DustPolicy, make_policy
from dust_rl.data import DemoDataset
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.data.features import dataset_policy_kwargs, env_state_width
from dust_rl.train.readout.aux_frames import FIRST_SEED, HELDOUT_FIRST_SEED, AuxFrameBatches, render_aux_frames
from dust_rl.train.readout.warmup import heldout_loss, warm_up_readout

pytestmark = pytest.mark.usefixtures("one_thread")


READOUTS = {"pixel keypoints": {"keypoints": 2, "keypoint_source": "pixels"}, "tokens": {"readout": "tokens"}}


def readout_policy(demo_dir, tiny_encoder, minilm, readout: str = "pixel keypoints") -> tuple[DemoDataset, DustPolicy]:
    """A tiny policy with a state read-out (:data:`READOUTS`) that frames can train, for the demo dataset."""
    dataset = DemoDataset(demo_dir)
    torch.manual_seed(0)
    policy = make_policy(image_encoder=tiny_encoder, text_encoder=minilm, **dataset_policy_kwargs(dataset),
                         horizon=6, d_model=32, n_heads=2, n_mmdit=2, n_dit=0, **READOUTS[readout],
                         aux_state_dim=env_state_width(dataset), lambda_aux=1.0)
    return dataset, policy


def aux_frames(dataset: DemoDataset, policy: DustPolicy, first_seed: int = FIRST_SEED) -> AuxFrameBatches:
    rows, instructions = render_aux_frames("DustFranka-v0", dataset.meta["env_kwargs"], dataset.tasks,
                                           policy.cameras, 4, env_state_width(dataset), first_seed=first_seed,
                                           progress=False)
    return AuxFrameBatches(rows, instructions, policy, EnvStateNorm.of_dataset(dataset))


@pytest.mark.parametrize(("with_demos", "readout"), [(True, "pixel keypoints"), (False, "pixel keypoints"),
                                                     (False, "tokens")])
def test_warm_up_fits_the_readout_alone_then_freezes_it(with_demos, readout, demo_dir, tiny_encoder, minilm):
    dataset, policy = readout_policy(demo_dir, tiny_encoder, minilm, readout)
    aux = aux_frames(dataset, policy)
    frames = aux.sample(4)  # the demonstration rows are stood in for by aux frames: the loss reads the same keys
    before = policy.readout_loss(frames).item()
    agent = {k: v.clone() for k, v in policy.model.state_dict().items()}
    logged = {}
    warm_up_readout(policy, (lambda: frames) if with_demos else None, aux, 100, 3e-3,
                    lambda scalars, step: logged.update({step: scalars}), batch_size=8, progress=False)
    assert policy.readout_loss(frames).item() < 0.5 * before
    expected = {"warmup/loss_aux_frames", "warmup/lr"} | ({"warmup/loss_aux"} if with_demos else set())
    assert sorted(logged) == [100] and set(logged[100]) == expected and logged[100]["warmup/lr"] == 3e-3
    assert not any(p.requires_grad or p.grad is not None for p in policy.readout.frame_modules().parameters())
    assert all(p.requires_grad for p in policy.model.parameters())
    assert all(torch.equal(v, agent[k]) for k, v in policy.model.state_dict().items())


def test_warm_up_keeps_the_weights_that_read_held_out_frames_best(demo_dir, tiny_encoder, minilm):
    dataset, policy = readout_policy(demo_dir, tiny_encoder, minilm)
    heldout, logged = aux_frames(dataset, policy, HELDOUT_FIRST_SEED), {}
    # A learning rate far too high makes the held-out error jump around: the last weights are not the best.
    warm_up_readout(policy, None, aux_frames(dataset, policy), 8, 0.3,
                    lambda scalars, step: logged.update({step: scalars}), batch_size=4, heldout=heldout, log_every=1,
                    progress=False)
    errors = [logged[step]["warmup/loss_aux_frames_heldout"] for step in sorted(logged)]
    assert len(errors) == 8 and min(errors) < errors[-1]
    assert heldout_loss(policy, heldout) == pytest.approx(min(errors), rel=1e-6)
