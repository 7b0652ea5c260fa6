"""Every data key the project reads or writes, declared once.

torchrl's VLA schema names the canonical ones (camera frames, robot state,
instruction, action chunk, padding mask); this module re-exports them and
adds the few DUST and the datasets need. Gymnasium observations and LeRobot
features use the same keys joined by dots (:func:`flat_name`):
``("observation", "state")`` is ``"observation.state"``. Nothing here
imports the envs or the agents, so both can import it.
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
READOUT_ESTIMATE_KEY = "env_state_estimate"  # a batch's read-out estimate of the normalised object state

__all__ = ["ACTION_CHUNK_KEY", "ACTION_IS_PAD_KEY", "ACTION_KEY", "ACTION_NOISE_KEY", "ENV_STATE_KEY",
           "EXPERT_ACTION_KEY", "FUTURE_CHUNK_KEY", "FUTURE_KEY", "IMAGE_KEY", "INSTRUCTION_BYTES_KEY",
           "INSTRUCTION_KEY", "PREDICTED_FUTURE_KEY", "SEED_KEY", "STATE_KEY", "STEP_KEY", "SUCCESS_KEY",
           "TASK_INDEX_KEY", "flat_name"]


def flat_name(key: NestedKey) -> str:
    """The gymnasium/LeRobot name of a key: ``("observation", "state")`` -> ``"observation.state"``."""
    return key if isinstance(key, str) else ".".join(key)
