"""Every data key the project reads or writes, declared once.

torchrl's VLA schema names the canonical ones (camera frames, robot state,
instruction, action chunk, padding mask); this module re-exports them and
adds the few DUST and the datasets need, and those of the model batch the
agents build and the data, training and RL code read and fill (the table in
:mod:`dust_rl.agents.policy`). Gymnasium observations and LeRobot features use
the same keys joined by dots (:func:`flat_name`): ``("observation", "state")``
is ``"observation.state"``. Nothing here imports the envs or the agents, so
both can import it.
"""

from __future__ import annotations

from tensordict.utils import NestedKey
from torchrl.data.vla.schema import (
    ACTION_CHUNK_KEY,
    ACTION_IS_PAD_KEY,
    ACTION_KEY,
    IMAGE_KEY,
    INSTRUCTION_KEY,
    STATE_KEY,
)

ENV_STATE_KEY = ("observation", "environment_state")  # privileged object state (never given to a policy)
EXPERT_ACTION_KEY = "expert_action"  # the scripted expert's label (differs from "action" under DART noise)
FUTURE_KEY = "future"  # a training window's observation H rows after its first
PREDICTED_FUTURE_KEY = ("dust", "future_tokens")  # the frozen tokens of the frame after the chunk, as sampled
FUTURE_CHUNK_KEY = ("dust", "future_chunk")  # the same, repeated along the chunk for the executor's cache
ACTION_NOISE_KEY = ("dust", "action_noise")  # the initial action noise a chunk is sampled from (steering)
SEED_KEY = "episode_seed"  # the reset seed of the episode a row belongs to
# The instruction as zero-padded UTF-8 bytes: a string does not survive torchrl's multi-process collectors
# (each worker's first one sticks in the shared buffer), a tensor does.
INSTRUCTION_BYTES_KEY = "instruction_utf8"
SUCCESS_KEY = "is_success"
STEP_KEY = "step_count"  # steps since the episode's reset
TASK_INDEX_KEY = "task_index"  # a rendered aux frame's task, an index into its dataset's tasks

# The model batch: flat [B] TensorDicts of frozen features and normalised values, never an env's; BATCH_ names one
# whose env-level name above is taken.
IMAGE_TOKENS_KEY = "image_tokens"  # each camera's frozen tokens on the token grid
TEXT_TOKENS_KEY = "text_tokens"  # the instruction's frozen tokens
TEXT_MASK_KEY = "text_mask"  # True for real instruction tokens
PIXELS_KEY = "pixels"  # the frames themselves, for pixel keypoints
BATCH_STATE_KEY = "state"  # the normalised robot state (with the read-out's estimate where the trunk reads it)
BATCH_ACTION_CHUNK_KEY = "action_chunk"  # the normalised chunk to learn, or a plan's chunk
FUTURE_TOKENS_KEY = "future_tokens"  # the world model's frame after the chunk: to learn, or a plan's
FUTURE_IS_CLAMPED_KEY = "future_is_clamped"  # the frame after the chunk lies past the episode's end
HAS_ACTION_KEY = "has_action"  # False for an action-free row (its action tokens are pure noise)
BATCH_ENV_STATE_KEY = "env_state"  # the normalised object state the read-out learns
READOUT_ESTIMATE_KEY = "env_state_estimate"  # the read-out's estimate of the normalised object state
COND_TOKENS_KEY = "cond_tokens"  # the projected tokens the trunk is conditioned on
COND_MASK_KEY = "cond_mask"  # True for real condition tokens
BATCH_ACTION_NOISE_KEY = "action_noise"  # a plan's initial action noise instead of a drawn one
VISION_NOISE_KEY = "vision_noise"  # a plan's initial vision noise instead of a drawn one

__all__ = ["ACTION_CHUNK_KEY", "ACTION_IS_PAD_KEY", "ACTION_KEY", "ACTION_NOISE_KEY", "BATCH_ACTION_CHUNK_KEY",
           "BATCH_ACTION_NOISE_KEY", "BATCH_ENV_STATE_KEY", "BATCH_STATE_KEY", "COND_MASK_KEY", "COND_TOKENS_KEY",
           "ENV_STATE_KEY", "EXPERT_ACTION_KEY", "FUTURE_CHUNK_KEY", "FUTURE_IS_CLAMPED_KEY", "FUTURE_KEY",
           "FUTURE_TOKENS_KEY", "HAS_ACTION_KEY", "IMAGE_KEY", "IMAGE_TOKENS_KEY", "INSTRUCTION_BYTES_KEY",
           "INSTRUCTION_KEY", "PIXELS_KEY", "PREDICTED_FUTURE_KEY", "READOUT_ESTIMATE_KEY", "SEED_KEY", "STATE_KEY",
           "STEP_KEY", "SUCCESS_KEY", "TASK_INDEX_KEY", "TEXT_MASK_KEY", "TEXT_TOKENS_KEY", "VISION_NOISE_KEY",
           "flat_name"]


def flat_name(key: NestedKey) -> str:
    """The gymnasium/LeRobot name of a key: ``("observation", "state")`` -> ``"observation.state"``."""
    return key if isinstance(key, str) else ".".join(key)
