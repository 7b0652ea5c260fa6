"""Train the state read-out (and its pixel keypoints) alone first, then hold it fixed while the policy learns.

Trained together with the action loss, the read-out does not localise the
target cube well enough to grasp it: after 3,000 steps with 3,000 aux frames
its estimate was still 12.8 cm from the target at step 0 of validation
episodes (pick_place; docs/franka_results.md). The same network trained on nothing but the
read-out error, at lr 1e-3, keeps improving for thousands of steps
(``experiments/pixel_probe.py``: 12.2 cm after 500 steps, 4.1 cm after 3,000,
still falling). So ``--readout.warmup-steps N`` first fits the keypoint networks and
the read-out for N steps on aux frames (and, unless ``--readout.no-demos``,
demonstration rows in half of each batch), then freezes them: a locator
trained on the simulator's labels, as a pose-estimation stage would be, whose
keypoints and estimate (``--model.aux-state-input``) the policy reads but cannot
move. Measured on pick_place validation episodes (docs/franka_results.md): with demonstration
rows the 200 training layouts are learnt by heart and the estimate is 8 cm
off at step 0; on aux frames alone 3.1 cm, but 12-15 cm once the cube is
lifted (random arm motions never lift it). Neither run's policy grasped
(2/20 and 0/20).

With held-out aux frames (``dust-rl train`` renders 256 from other seeds) the weights of the lowest
held-out error are kept, not the last ones: with 5,000 frames the read-out learnt them by heart (4.9 cm on
its frames, 11.7 cm on fresh ones; docs/franka_results.md).

A resumed run skips the warm-up (its checkpoint holds the warmed weights); a
run stopped during the warm-up repeats it from the start, which gives the same
weights (the warm-up draws from the run's seeded global generator).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.train.optim import adamw
from dust_rl.train.readout.aux_frames import AuxFrameBatches

LOG_EVERY = 100


def warm_up_readout(policy: DustPolicy, demo_batch: Callable[[], TensorDictBase] | None, aux: AuxFrameBatches,
                    steps: int, lr: float, log: Callable[[dict[str, float], int], None], batch_size: int = 64,
                    *, heldout: AuxFrameBatches | None = None, log_every: int = LOG_EVERY,
                    progress: bool = True) -> None:
    """Fit ``policy``'s read-out (and its pixel keypoints) for ``steps`` steps, then freeze them.

    Args:
        policy: a policy with a read-out on image tokens or pixel keypoints, in training mode (pixel frames are
            shifted at random).
        demo_batch: draws a feature batch of demonstration rows (with ``pixels`` and ``env_state``); None: aux
            frames only.
        aux: aux frames; each step draws ``batch_size`` of them.
        steps: optimiser steps (AdamW at the constant rate ``lr``).
        log: receives ``warmup/loss_aux_frames`` and ``warmup/lr`` (and ``warmup/loss_aux`` on demonstration rows,
            and ``warmup/loss_aux_frames_heldout``) every ``log_every`` steps.
        heldout: aux frames never fitted, whose error (frames unshifted, no random draws) tells learning the
            positions from learning the frames by heart; the weights of its lowest error (checked every
            ``log_every`` steps) are the ones kept.
        progress: show a progress bar.
    """
    modules = policy.readout.frame_modules()
    modules.requires_grad_(True)
    optimizer = adamw(list(modules.parameters()), lr)
    best = (float("inf"), None)  # the lowest held-out error and the weights that reached it
    for step in tqdm(range(1, steps + 1), desc="read-out warm-up", disable=not progress):
        losses = {"warmup/loss_aux_frames": policy.readout_loss(aux.sample(batch_size))}
        if demo_batch is not None:
            losses["warmup/loss_aux"] = policy.readout_loss(demo_batch())
        optimizer.zero_grad(set_to_none=True)
        sum(losses.values()).backward()
        optimizer.step()
        if step % log_every == 0 or step == steps:
            scalars = {k: v.item() for k, v in losses.items()} | {"warmup/lr": optimizer.param_groups[0]["lr"]}
            if heldout is not None:
                scalars["warmup/loss_aux_frames_heldout"] = error = heldout_loss(policy, heldout)
                if error < best[0]:
                    best = (error, {k: v.clone() for k, v in modules.state_dict().items()})
            log(scalars, step)
    if best[1] is not None:  # early stopping: the weights that generalised best to the held-out frames
        modules.load_state_dict(best[1])
    optimizer.zero_grad(set_to_none=True)  # a stale gradient would still count in the policy's gradient clipping
    modules.requires_grad_(False)


@torch.no_grad()
def heldout_loss(policy: DustPolicy, frames: AuxFrameBatches) -> float:
    """The read-out's error on every frame of ``frames``, as acting sees them (evaluation mode)."""
    was_training = policy.training
    policy.eval()
    try:
        return policy.readout_loss(frames.rows(torch.arange(len(frames)))).item()
    finally:
        policy.train(was_training)
