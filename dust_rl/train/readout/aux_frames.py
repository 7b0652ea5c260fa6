"""Frames whose objects do not follow the arm, to teach the privileged read-out where things are.

On expert demonstrations the gripper holds the target cube in nearly nine
rows of ten, so a read-out of the objects' state fitted on demonstrations
learns "the target is where the gripper is": on 40 validation episodes it
is 15 cm from the target cube at step 0 (where the gripper is 17 cm away),
no better than guessing, with pixel keypoints and frozen features alike
(``experiments/readout_error.py``, docs/franka_results.md). These frames break that shortcut:
each is a random reset of a training task followed by 0..39 uniformly random
actions, so the cubes lie anywhere relative to the arm. ``--readout.aux-frames N``
renders N of them once at the start of training and adds their read-out
error to every step's loss beside the demonstrations'.

Random motions never lift a cube, so a read-out trained on them alone is
3 cm off before the grasp but 12-15 cm off once the cube is carried
(docs/franka_results.md). Frames taken along the scripted expert's episode,
close-ups where it is about to grasp, and either with the loose objects moved
away from the gripper were each measured against random motions only and did
worse (docs/franka_results.md); more random frames and a finer read-out are
what helped, so random motions are the only kind.

Seeds start at :data:`FIRST_SEED`, away from the demonstration (0..),
validation (5000..) and held-out (10000..) seeds, so the frames never show a
layout the policy is scored on.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.envs.env import DustEnv
from dust_rl.envs.factory import make_env
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY, INSTRUCTION_KEY, TASK_INDEX_KEY, flat_name

FIRST_SEED = 1_000_000
HELDOUT_FIRST_SEED = 2_000_000  # frames that only measure the read-out (never fitted)
HELDOUT_FRAMES = 256
MAX_RANDOM_STEPS = 40


def render_aux_frames(env_id: str, env_kwargs: dict, tasks: list[str], cameras: list[str], count: int,
                      env_state_width: int, seed: int = 0, first_seed: int = FIRST_SEED,
                      progress: bool = True) -> tuple[TensorDict, list[str]]:
    """``count`` frames of random resets and random arm motions, tasks in turn.

    Args:
        env_id, env_kwargs: the env the training data came from.
        tasks: its tasks.
        cameras: the policy's cameras.
        count: frames to render.
        env_state_width: the dataset's (padded) width of the object state; shorter states are zero-padded.
        seed: offsets the frames' seeds (first_seed + seed * count + i), so runs can differ.
        first_seed: :data:`FIRST_SEED` for frames to fit, :data:`HELDOUT_FIRST_SEED` for frames that measure.
        progress: show a progress bar.

    Returns:
        (rows with ``(observation, image, cam)`` uint8 [count, 3, H, W], the object state [count, S] and
        ``task_index`` [count] (into ``tasks``), the instruction of each frame).
    """
    envs = {task: make_env(env_id, {**env_kwargs, "task": task}) for task in tasks}
    frames = {cam: [] for cam in cameras}
    states, instructions = torch.zeros(count, env_state_width), []
    try:
        for i in tqdm(range(count), desc="aux frames", disable=not progress):
            frame_seed = first_seed + seed * count + i
            env = envs[tasks[i % len(tasks)]]  # frame i shows task i % len(tasks): its task_index
            rng = np.random.default_rng(frame_seed)
            env.reset(seed=frame_seed)
            sim = env.unwrapped  # steps without rendering; only the frame at the end is drawn
            _random_steps(sim, rng, int(rng.integers(0, MAX_RANDOM_STEPS)))
            obs = sim.observe()
            for cam in cameras:
                frames[cam].append(torch.from_numpy(obs[f"{flat_name(IMAGE_KEY)}.{cam}"]).permute(2, 0, 1))
            state = torch.from_numpy(obs[flat_name(ENV_STATE_KEY)])
            states[i, :state.shape[0]] = state
            instructions.append(obs[INSTRUCTION_KEY])
    finally:
        for env in envs.values():
            env.close()
    rows = TensorDict({**{(*IMAGE_KEY, cam): torch.stack(frames[cam]) for cam in cameras}, ENV_STATE_KEY: states,
                       TASK_INDEX_KEY: torch.arange(count) % len(tasks)}, batch_size=[count])
    return rows, instructions


def _random_steps(sim: DustEnv, rng: np.random.Generator, steps: int) -> None:
    """``steps`` uniformly random actions, or fewer if the episode ends (a time limit, an unstable simulation)."""
    for _ in range(steps):
        if sim.advance(rng.uniform(-1.0, 1.0, sim.action_space.shape).astype(np.float32))[1]:
            break


class AuxFrameBatches:
    """Random batches of aux frames in the form :meth:`~dust_rl.agents.DustPolicy.readout_loss` reads.

    Args:
        rows, instructions: :func:`render_aux_frames` output.
        policy: supplies the cameras, the text encoder and (for a token read-out) the frozen image encoder.
        env_state_norm: normalises the object state (the training data's statistics, task by task; ``rows``'
            ``task_index`` points into its ``tasks``).
        encode: frames [F, C, 3, H, W] to the policy's frozen tokens [F, C, N, Dv], for a token read-out;
            default :func:`encode_frames` (training passes one that reads tokens an earlier run stored).
    """

    def __init__(self, rows: TensorDict, instructions: list[str], policy: DustPolicy,
                 env_state_norm: EnvStateNorm, encode: Callable[[torch.Tensor], torch.Tensor] | None = None) -> None:
        self.device = policy.weights_device
        # What the read-out reads, made once: the frozen tokens (``encode``) or the raw frames (shifted per draw).
        self.frame_key = "image_tokens" if policy.config.readout == "tokens" else "pixels"
        frames = policy.frames(rows)
        if self.frame_key == "image_tokens":
            frames = encode(frames) if encode is not None else encode_frames(policy, frames)
        self.frames = frames
        distinct = {text: i for i, text in enumerate(dict.fromkeys(instructions))}  # tokens once per instruction
        self.text_tokens, self.text_mask = policy.backbone.text_tokens(list(distinct))
        self.instruction_index = torch.tensor([distinct[text] for text in instructions])
        self.task_index = rows.get(TASK_INDEX_KEY)
        self.env_state = env_state_norm.normalize(rows.get(ENV_STATE_KEY), self.task_index)

    def __len__(self) -> int:
        return self.frames.shape[0]

    def sample(self, batch_size: int) -> TensorDict:
        """``batch_size`` frames drawn with replacement (torch's global generator, as the demo windows)."""
        return self.rows(torch.randint(0, len(self), (batch_size,)))

    def rows(self, index: torch.Tensor) -> TensorDict:
        """The frames at ``index`` (all of them: ``rows(torch.arange(len(batches)))``)."""
        text = self.instruction_index[index]
        return TensorDict({self.frame_key: self.frames[index], "text_tokens": self.text_tokens[text],
                           "text_mask": self.text_mask[text], "env_state": self.env_state[index]},
                          batch_size=[len(index)], device=self.device)


@torch.no_grad()
def encode_frames(policy: DustPolicy, frames: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """Frozen condition tokens [F, C, N, Dv] of frames [F, C, 3, H, W], ``chunk`` frames at a time."""
    return torch.cat([policy.frame_tokens(frames[i:i + chunk].to(policy.weights_device)).cpu()
                      for i in range(0, len(frames), chunk)])
