"""Frames whose objects do not follow the arm, to teach the privileged read-out where things are.

On expert demonstrations the gripper holds the target cube in nearly nine
rows of ten, so a read-out of the objects' state fitted on demonstrations
learns "the target is where the gripper is": on 40 validation episodes it
is 15 cm from the target cube at step 0 (where the gripper is 17 cm away),
no better than guessing, with pixel keypoints and frozen features alike
(``experiments/readout_error.py``, docs/franka_results.md). These frames break that shortcut:
each is a random reset of a training task with the arm placed where a walk of 0..39 uniformly random actions
from home would have commanded it, so the cubes lie anywhere relative to the arm. ``--readout.aux-frames N``
renders N of them once at the start of training and adds their read-out error to every step's loss beside the
demonstrations'.

The arm is placed, not walked (:meth:`~dust_rl.envs.env.DustEnv.place_end_effectors`: ten IK steps, the joints
set, two control periods of physics for the fingers): a walked frame cost 19.7 ms in the main job on a 2-core x86
CPU (a reset that rendered two frames nobody used, then ~20 control steps of an IK solve and 25 physics substeps
each), a placed one 7.2 ms, of which rendering the two cameras is 2.5 (BENCHMARKS.md). What a placement leaves out
is the walk's pushes: a walk rarely reached an object from home. The main job scored the same with placed frames
(98%, 49/50 held-out; docs/results/2026-12-02-speed-and-perception.md).

Random motions never lift a cube, so a read-out trained on them alone is
3 cm off before the grasp but 12-15 cm off once the cube is carried
(docs/franka_results.md). Frames taken along the scripted expert's episode,
close-ups where it is about to grasp, and either with the loose objects moved
away from the gripper were each measured against random motions only and did
worse with the read-out of that time (docs/franka_results.md); ``close_up_fraction`` places that share of the
frames at a step of the task's expert plan (hover, grasp, lift, carry, place) with 1 cm of jitter, for read-outs
that may use them, and is off by default.

Seeds start at :data:`FIRST_SEED`, away from the demonstration (0..),
validation (5000..) and held-out (10000..) seeds, so the frames never show a
layout the policy is scored on.
"""

from __future__ import annotations

from collections.abc import Callable

import mink
import mujoco
import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from dust_rl.agents import DustPolicy
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.envs.env import ACTION_WIDTH, CLOSURE, MAX_ROTATION, MAX_TRANSLATION, DustEnv, axis_angle_to_quat
from dust_rl.envs.experts import Waypoint
from dust_rl.envs.factory import make_env
from dust_rl.keys import (
    BATCH_ENV_STATE_KEY,
    BATCH_STATE_KEY,
    ENV_STATE_KEY,
    IMAGE_KEY,
    IMAGE_TOKENS_KEY,
    INSTRUCTION_KEY,
    PIXELS_KEY,
    STATE_KEY,
    TASK_INDEX_KEY,
    TEXT_MASK_KEY,
    TEXT_TOKENS_KEY,
    flat_name,
)

FIRST_SEED = 1_000_000
HELDOUT_FIRST_SEED = 2_000_000  # frames that only measure the read-out (never fitted)
HELDOUT_FRAMES = 256
MAX_RANDOM_STEPS = 40  # a placed frame's arm is where a walk of up to this many random actions would command it
CLOSE_UP_JITTER = 0.01  # metres (standard deviation per axis) around a close-up's expert waypoint


def render_aux_frames(env_id: str, env_kwargs: dict, tasks: list[str], cameras: list[str], count: int,
                      env_state_width: int, seed: int = 0, first_seed: int = FIRST_SEED,
                      close_up_fraction: float = 0.0, progress: bool = True) -> tuple[TensorDict, list[str]]:
    """``count`` frames of random resets with the arm placed at random, tasks in turn.

    Args:
        env_id, env_kwargs: the env the training data came from.
        tasks: its tasks.
        cameras: the policy's cameras.
        count: frames to render.
        env_state_width: the dataset's (padded) width of the object state; shorter states are zero-padded.
        seed: offsets the frames' seeds (first_seed + seed * count + i), so runs can differ.
        first_seed: :data:`FIRST_SEED` for frames to fit, :data:`HELDOUT_FIRST_SEED` for frames that measure.
        close_up_fraction: the share of frames placed at a step of the expert's plan rather than at a random
            walk's end (each frame draws which from its own seed).
        progress: show a progress bar.

    Returns:
        (rows with ``(observation, image, cam)`` uint8 [count, 3, H, W], the object state [count, S], the robot
        state [count, Ds] and ``task_index`` [count] (into ``tasks``), the instruction of each frame).
    """
    envs = {task: make_env(env_id, {**env_kwargs, "task": task}) for task in tasks}
    frames = {cam: [] for cam in cameras}
    states, robot_states, instructions = torch.zeros(count, env_state_width), [], []
    try:
        for i in tqdm(range(count), desc="aux frames", disable=not progress):
            frame_seed = first_seed + seed * count + i
            sim = envs[tasks[i % len(tasks)]].unwrapped  # frame i shows task i % len(tasks): its task_index
            rng = np.random.default_rng(frame_seed)
            sim.reset_unobserved(seed=frame_seed)
            close_up = rng.uniform() < close_up_fraction
            sim.place_end_effectors(*(_close_up_targets if close_up else _walk_targets)(sim, rng))
            obs = sim.observe()
            for cam in cameras:
                frames[cam].append(torch.from_numpy(obs[f"{flat_name(IMAGE_KEY)}.{cam}"]).permute(2, 0, 1))
            state = torch.from_numpy(obs[flat_name(ENV_STATE_KEY)])
            states[i, :state.shape[0]] = state
            robot_states.append(torch.from_numpy(obs[flat_name(STATE_KEY)]))
            instructions.append(obs[INSTRUCTION_KEY])
    finally:
        for env in envs.values():
            env.close()
    rows = TensorDict({**{(*IMAGE_KEY, cam): torch.stack(frames[cam]) for cam in cameras}, ENV_STATE_KEY: states,
                       STATE_KEY: torch.stack(robot_states), TASK_INDEX_KEY: torch.arange(count) % len(tasks)},
                      batch_size=[count])
    return rows, instructions


Targets = tuple[list[mink.SE3], list[float]]  # a pose and a closure per end effector


def _walk_targets(sim: DustEnv, rng: np.random.Generator) -> Targets:
    """Where 0..MAX_RANDOM_STEPS - 1 uniformly random delta actions would have commanded each end effector from
    where it is, tracked perfectly: their translations summed, their turns composed, the last one's closure (open
    after none)."""
    actions = rng.uniform(-1.0, 1.0, (int(rng.integers(0, MAX_RANDOM_STEPS)), *sim.action_space.shape))
    targets, closures = [], []
    for index, (position, rotation) in enumerate(sim.end_effector_poses()):
        own = actions[:, ACTION_WIDTH * index: ACTION_WIDTH * (index + 1)]
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, rotation.ravel())
        for turn in own[:, 3:6]:
            mujoco.mju_mulQuat(quat, axis_angle_to_quat(turn * MAX_ROTATION), quat.copy())
        targets.append(mink.SE3(np.r_[quat, position + own[:, :3].sum(axis=0) * MAX_TRANSLATION]))
        closures.append((own[-1, CLOSURE] + 1.0) / 2.0 if len(own) else 0.0)
    return targets, closures


def _close_up_targets(sim: DustEnv, rng: np.random.Generator) -> Targets:
    """A random step of the task's expert plan from this layout, its positions jittered by
    :data:`CLOSE_UP_JITTER`: the gripper hovering over, at, or carrying-height above what the task is about."""
    plan = sim.task.expert_plan(sim.model, sim.data)
    step = plan[int(rng.integers(0, len(plan)))]
    waypoints = [step] if isinstance(step, Waypoint) else list(step)
    targets = [mink.SE3.from_rotation_and_translation(mink.SO3.from_matrix(ee.grasp_frame(waypoint.yaw)),
                                                      waypoint.target() + rng.normal(0.0, CLOSE_UP_JITTER, 3))
               for ee, waypoint in zip(sim.robot.end_effectors, waypoints, strict=True)]
    return targets, [waypoint.closure for waypoint in waypoints]


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
        self.frame_key = IMAGE_TOKENS_KEY if policy.config.readout == "tokens" else PIXELS_KEY
        frames = policy.frames(rows)
        if self.frame_key == IMAGE_TOKENS_KEY:
            frames = encode(frames) if encode is not None else encode_frames(policy, frames)
        self.frames = frames
        distinct = {text: i for i, text in enumerate(dict.fromkeys(instructions))}  # tokens once per instruction
        self.text_tokens, self.text_mask = policy.backbone.text_tokens(list(distinct))
        self.instruction_index = torch.tensor([distinct[text] for text in instructions])
        self.task_index = rows.get(TASK_INDEX_KEY)
        self.env_state = env_state_norm.normalize(rows.get(ENV_STATE_KEY), self.task_index)
        self.state = policy.normalizer.normalize_state(rows.get(STATE_KEY).float())

    def __len__(self) -> int:
        return self.frames.shape[0]

    def sample(self, batch_size: int) -> TensorDict:
        """``batch_size`` frames drawn with replacement (torch's global generator, as the demo windows)."""
        return self.rows(torch.randint(0, len(self), (batch_size,)))

    def rows(self, index: torch.Tensor) -> TensorDict:
        """The frames at ``index`` (all of them: ``rows(torch.arange(len(batches)))``)."""
        text = self.instruction_index[index]
        return TensorDict({self.frame_key: self.frames[index], TEXT_TOKENS_KEY: self.text_tokens[text],
                           TEXT_MASK_KEY: self.text_mask[text], BATCH_ENV_STATE_KEY: self.env_state[index],
                           BATCH_STATE_KEY: self.state[index]},
                          batch_size=[len(index)], device=self.device)


@torch.no_grad()
def encode_frames(policy: DustPolicy, frames: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """Frozen condition tokens [F, C, N, Dv] of frames [F, C, 3, H, W], ``chunk`` frames at a time."""
    return torch.cat([policy.frame_tokens(frames[i:i + chunk].to(policy.weights_device)).cpu()
                      for i in range(0, len(frames), chunk)])
