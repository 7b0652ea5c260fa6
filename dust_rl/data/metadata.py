"""Dataset metadata: collection config, env spec and versions, and their checks.

``meta.json`` is written before the first episode, so a second ``collect`` into the
same folder can tell a resume (same config) from a conflicting request (a different
env, image size, noise...) and refuse the latter instead of mixing data.
"""

from __future__ import annotations

import collections
import pathlib

import gymnasium as gym

from dust_rl.envs.env import FLAT_STATE_KEY, STATE_MODE_KEYS
from dust_rl.errors import DatasetError
from dust_rl.storage.config_json import package_versions
from dust_rl.storage.paths import inside

from .layout import FORMAT_VERSION, META_FILE, read_json, write_json_atomic

# Config entries that must be equal to append to an existing dataset.
FIXED_CONFIG = ("env_id", "env_kwargs", "start_seed", "noise_std", "keep_failed", "policy")
_IMAGE_PREFIX = "observation.image."


# What recorded_env_spec records.
SPEC_KEYS = ("cameras", "image_shape", "state_dim", "action_dim", "control_hz", "fps")


def recorded_env_spec(env: gym.Env) -> dict:
    """The parts of an env that a dataset's arrays depend on (cameras, shapes, rates)."""
    spaces = env.observation_space.spaces
    cameras = [key.removeprefix(_IMAGE_PREFIX) for key in spaces if key.startswith(_IMAGE_PREFIX)]
    unwrapped = env.unwrapped
    return {
        "cameras": cameras,
        "image_shape": list(spaces[_IMAGE_PREFIX + cameras[0]].shape) if cameras else None,
        "state_dim": int(spaces.get(FLAT_STATE_KEY, spaces.get(STATE_MODE_KEYS[FLAT_STATE_KEY])).shape[0]),
        "action_dim": int(env.action_space.shape[0]),
        "control_hz": round(1.0 / unwrapped.control_dt, 6),
        "fps": int(unwrapped.metadata["render_fps"]),
    }


def spec_mismatches(expected: dict, actual: dict) -> list[str]:
    """Human-readable differences between two :func:`recorded_env_spec` results."""
    return [f"{key}: dataset has {expected.get(key)!r}, env has {actual[key]!r}"
            for key in actual if expected.get(key) != actual[key]]


def read_meta(root: pathlib.Path) -> dict:
    """``meta.json`` of the dataset at ``root``, with its format version checked and its data folder
    confined to ``root`` (see :func:`~dust_rl.storage.paths.inside`)."""
    path = root / META_FILE
    if not path.is_file():
        raise DatasetError(f"{root}: not a dust-rl dataset (no {META_FILE})")
    try:
        meta = read_json(path)
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: unreadable ({err})") from err
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: unreadable (a JSON {type(meta).__name__}, not an object)")
    if meta.get("format_version") != FORMAT_VERSION:
        raise DatasetError(f"{path}: dataset format version {meta.get('format_version')!r}; "
                           f"this dust-rl reads version {FORMAT_VERSION}")
    if meta.get("data") is not None:
        inside(root, meta["data"], path)
    return meta


def open_meta(root: pathlib.Path, config: dict, tasks: list[str], episodes: int, spec: dict) -> dict:
    """Create ``meta.json`` or check that ``config``/``spec`` match the existing one; record the request.

    Args:
        config: the :data:`FIXED_CONFIG` entries of this collection.
        tasks: tasks requested now; they join the dataset with ``episodes`` each, or with as many
            as its consolidated copy already holds if that is more (finalising fewer would delete rows).
        spec: :func:`recorded_env_spec` of the env about to be collected.
    """
    if (root / META_FILE).exists():
        meta = read_meta(root)
        if meta.get("source"):
            raise DatasetError(f"{root} was imported from {meta['source']}; collect into a new folder")
        problems = [f"{key}: dataset has {meta[key]!r}, requested {config[key]!r}"
                    for key in FIXED_CONFIG if meta.get(key) != config[key]]
        problems += spec_mismatches(meta["spec"], spec)
        if problems:
            raise DatasetError(f"{root} holds a different collection; use another --out or the same settings: "
                               + "; ".join(problems))
    else:
        meta = {"format_version": FORMAT_VERSION, **config, "spec": spec, "episodes_per_task": {}, "data": None}
    held = collections.Counter(e["task"] for e in meta.get("episodes", []) if e["success"])
    meta["episodes_per_task"] = {**meta["episodes_per_task"], **{task: max(episodes, held[task]) for task in tasks}}
    meta["versions"] = package_versions()
    write_json_atomic(root / META_FILE, meta)
    return meta
