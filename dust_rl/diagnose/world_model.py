"""Does the world model predict the future, and could the actions use one? ``dust-rl diagnose world-model``.

DUST is worth its vision stream only if (1) the stream predicts the frame H steps on better than trivial
guesses and (2) the action stream reads that prediction. Both are measured on windows of a dataset the policy
was not trained on (collect one on other seeds: ``dust-rl collect --seed 5000 ...``), in the trunk's own units
(standardised tokens, normalised actions):

1. **Skill of the vision stream.** For flow times tau_o in ``--tau-buckets`` equal buckets, the true future is
   noised to tau_o (the actions to the same level), and the stream's one-step estimate of the clean future,
   ``x_tau + (1 - tau) v_o``, is compared with two predictors that need no model: the targets' mean and the
   present frame (a zero change for ``future_target change``). ``skill = 1 - err / err_present``: above 0 the
   stream knows more than "nothing moves". The joint sample of the policy's own sampler is scored the same way.
2. **The oracle-future test.** Action chunks are sampled with the policy's sampler and the same action noise
   while the vision stream holds (a) its own joint sample, (b) the *true* future re-noised to each step's
   tau_o, (c) the present frame ("nothing moves", a zero change for a change target), re-noised the same way,
   (d) pure noise at tau_o = 0, (e) the true future of another episode of the same task, re-noised the same
   way. Scored: the chunk's error against the demonstration, and the action flow-matching loss with the
   vision stream held at the clean version of each (noise for (d)). If (b) does not beat (d), no better world
   model can help these actions; if it does, (a) - (b) is what a better world model could buy, (c) tells a
   future from a second view of the present (what a world model that predicts nothing could already give),
   and (e) a future that is read from one that only has to look like the task's.

Every number is a mean over episodes of the per-episode mean over windows, with a 95% interval from the normal
approximation over episodes (the windows of one episode are not independent); paired differences (same windows,
same noise) likewise, with the p-value of a zero mean.

| file | what |
|---|---|
| ``report.json`` | every number, per tau bucket and per condition, with the command and windows |
| ``report.md`` | the two tables (and both per task, for a dataset of several tasks) |
| ``world_model.png`` | error per tau bucket against the predictors; each condition's action error minus noise's |
| ``futures.png`` | predicted futures beside real ones, when a decoder draws them (:mod:`dust_rl.diagnose.futures`) |
"""

from __future__ import annotations

import math
import pathlib
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict
from torch import Tensor

from dust_rl.agents import DustPolicy, load_policy, schedule_for
from dust_rl.agents.model.flow_matching import interpolate, sample_tau, velocity_target
from dust_rl.agents.model.samplers import DenoiseStep
from dust_rl.data import DatasetError, DemoDataset, DemoWindows
from dust_rl.data.features import FeatureCache
from dust_rl.diagnose.futures import futures_figure
from dust_rl.errors import ConfigError, check_at_least
from dust_rl.evaluate.resampling import Resampling, apply_sampling, describe_sampler, resolved_sampler
from dust_rl.evaluate.video import decoder_for
from dust_rl.keys import FUTURE_IS_CLAMPED_KEY
from dust_rl.runtime.device import resolve_device
from dust_rl.runtime.settings import RuntimeSettings, runtime_field
from dust_rl.storage.atomic_files import atomic_write, write_json_atomic, write_text_atomic
from dust_rl.storage.config_json import config_json

CONDITIONS = {
    "own": "its own joint sample",
    "true": "the true future, re-noised to each step's tau_o",
    "present": "the present frame (nothing moves), re-noised",
    "noise": "pure noise (tau_o = 0)",
    "other": "another episode's future (same task), re-noised",
}
# The paired differences of the action error, by name: the first three read the test (can the actions read a
# future; a future, not only a second view of the present; what a better world model could buy).
PAIRS = {"true - noise": ("true", "noise"), "true - present": ("true", "present"), "own - true": ("own", "true"),
         "own - noise": ("own", "noise"), "present - noise": ("present", "noise"), "other - noise": ("other", "noise"),
         "true - other": ("true", "other")}
READINGS = tuple(PAIRS)[:3]
# Each tau bucket is one more pass of the trunk over every window: 50 resolve tau_o to 0.02 (the default 5 to 0.2)
# in ten times the default's time, while 100,000 would run for hours.
MAX_TAU_BUCKETS = 50

SliceSource = Callable[[TensorDict, Tensor], Callable[[DenoiseStep], tuple[Tensor, float]]]
"""Per slice of windows (its batch, its rows), the :data:`~dust_rl.agents.model.samplers.VisionSource` of its chunks."""


@dataclass
class WorldModelDiagnosis:
    """Measure a policy's world model on held-out windows: the vision stream's skill against trivial predictors,
    and the oracle-future test of whether its actions can use a future (`dust-rl diagnose world-model`)."""

    policy: pathlib.Path
    """Policy file (`dust-rl train`)."""
    dataset: pathlib.Path
    """Dataset of the policy's env and tasks whose episodes it was not trained on."""
    out: pathlib.Path = pathlib.Path("runs/diagnose/world_model")
    """Folder for `report.json`, `report.md` and `world_model.png`."""
    windows: int = 512
    """Windows drawn at random from the dataset (fewer if it has fewer rows)."""
    batch_size: int = 128
    """Windows per forward pass."""
    tau_buckets: int = 5
    """Equal buckets of tau_o in [0, 1] for the vision stream's error (at most 50: each is a pass over every
    window)."""
    seed: int = 0
    """Seed of the windows drawn and of every noise."""
    sampling: Resampling = None
    """The sampler of the policy's own samples: as the policy file says (the default), or `resample` with other
    settings, given after every other argument (`... resample --vision-step-ratio 4`: N_o = 16 vision steps)."""
    decoder: pathlib.Path | None = None
    """Token decoder file that draws the predicted futures in `futures.png` when the image encoder cannot decode
    its tokens (`dust-rl encoder fit-decoder`); default: `token_decoder.pt` beside the policy file, if there is one."""
    runtime: RuntimeSettings = runtime_field()
    """Where the policy runs (`--runtime.device`), its threads, the feature cache's progress bar; at fp32,
    uncompiled."""

    def __post_init__(self) -> None:
        check_at_least(self, 1, "windows", "batch_size", "tau_buckets")
        self.runtime.check_fp32("dust-rl diagnose world-model")
        if self.tau_buckets > MAX_TAU_BUCKETS:
            raise ConfigError(f"tau_buckets must be at most {MAX_TAU_BUCKETS} (each is one more pass over every "
                              f"window), got {self.tau_buckets}")


@dataclass
class Windows:
    """The diagnosed windows as the trunk sees them, with what the two tests need beside."""

    batch: TensorDict
    """The trunk's batch [N] (`cond_tokens`, `state`, `action_chunk`, `future_tokens` ...)."""
    present: Tensor | None
    """[N, N_o, Dv] the "nothing moves" prediction of `future_tokens` (None without a vision stream)."""
    episode: Tensor
    """[N] the dataset episode of each window (intervals are over episodes)."""
    other: Tensor | None
    """[N] index of a window of another episode of the same task (-1: none), for condition (e)."""
    task: Tensor
    """[N] the index of each window's task in `task_names`."""
    task_names: list[str]
    """The dataset's tasks."""

    def task_masks(self) -> dict[str, Tensor]:
        """Per task with windows, which windows are its; empty when they are all of one task (nothing to split)."""
        masks = {name: self.task == i for i, name in enumerate(self.task_names) if bool((self.task == i).any())}
        return masks if len(masks) > 1 else {}


def per_window_error(pred: Tensor, target: Tensor, valid: Tensor | None = None) -> Tensor:
    """Mean squared error of each window [B] over its valid rows (``valid`` [B, rows]) and features."""
    squared = (pred.float() - target.float()).square().mean(-1)
    if valid is None:
        return squared.flatten(1).mean(1)
    return torch.where(valid, squared, 0.0).sum(1) / valid.sum(1).clamp_min(1)


def mean_interval(values: Tensor, episode: Tensor) -> dict[str, float]:
    """Mean over episodes of each episode's mean of ``values`` [n], with its 95% interval (normal approximation
    over episodes: the windows of one episode are not independent draws), and the counts."""
    groups, index = torch.unique(episode.cpu(), return_inverse=True)
    sums = torch.zeros(len(groups), dtype=torch.float64).index_add_(0, index, values.detach().cpu().double())
    means = sums / torch.bincount(index, minlength=len(groups))
    n = len(means)
    mean = means.mean().item() if n else math.nan
    half = 1.96 * means.std().item() / math.sqrt(n) if n > 1 else math.nan
    return {"mean": mean, "ci95_low": mean - half, "ci95_high": mean + half, "episodes": n, "windows": len(values)}


def paired(first: Tensor, second: Tensor, episode: Tensor) -> dict[str, float]:
    """``first - second`` on the same windows (:func:`mean_interval`) and the two-sided p-value of a zero mean."""
    summary = mean_interval(first - second, episode)
    half = (summary["ci95_high"] - summary["mean"]) / 1.96
    summary["p"] = math.erfc(abs(summary["mean"]) / half / math.sqrt(2)) if half > 0 else math.nan
    return summary


def dataset_features(config: WorldModelDiagnosis, policy: DustPolicy) -> FeatureCache:
    """The frozen features of the diagnosed dataset (stored in its folder).

    Raises:
        DatasetError: the dataset's cameras or sizes do not fit the policy.
    """
    dataset = DemoDataset(config.dataset)
    dataset.check_fits_policy(policy.info, config.policy)
    return FeatureCache(dataset, policy, progress=config.runtime.progress, store=True)


def draw_windows(config: WorldModelDiagnosis, policy: DustPolicy) -> Windows:
    """``config.windows`` random windows of the dataset in the trunk's units (raises as :func:`dataset_features`)."""
    return windows_of(policy, dataset_features(config, policy), config.windows, config.seed, config.batch_size)


def windows_of(policy: DustPolicy, features: FeatureCache, count: int, seed: int, batch_size: int = 128) -> Windows:
    """``count`` windows of ``features``' dataset drawn with ``seed`` (torch's global generator is left as it
    was), in the trunk's units: the trunk's normalisation must be set before, and the windows hold for the
    weights of now (their condition tokens come from trained layers)."""
    dataset = features.dataset
    windows = DemoWindows(dataset, horizon=policy.config.horizon, future_offset=policy.config.future_steps,
                          batch_size=min(count, len(dataset)), images=False)
    parts, presents = [], []
    with torch.random.fork_rng(devices=[]), torch.no_grad():  # cached views may be drawn at random too
        torch.manual_seed(seed)
        drawn = windows.sample()
        for rows in drawn.split(batch_size):
            feature_batch = features.batch(rows)
            parts.append(policy._model_batch(feature_batch))
            if policy.config.has_vision:
                presents.append(present_frame(policy, feature_batch))
    rows = drawn.get("index")
    episode = torch.searchsorted(dataset.episode_starts, rows, right=True) - 1
    task = dataset.row_task_index[rows]
    if not policy.config.has_vision:
        return Windows(torch.cat(parts), None, episode, None, task, dataset.tasks)
    return Windows(torch.cat(parts), torch.cat(presents), episode, other_episode_windows(episode, task, seed),
                   task, dataset.tasks)


def present_frame(policy: DustPolicy, features: TensorDict) -> Tensor:
    """The world-model target if nothing moved: the present frame (a frame target), no change (a change target)."""
    present = policy.present_target(features)
    return present if policy.config.future_target == "frame" else torch.zeros_like(present)


def other_episode_windows(episode: Tensor, task: Tensor, seed: int) -> Tensor:
    """Per window, a random window of another episode of the same task (-1 where there is none)."""
    generator = torch.Generator().manual_seed(seed)
    other = torch.full_like(episode, -1)
    for i in range(len(episode)):
        candidates = torch.nonzero((task == task[i]) & (episode != episode[i])).flatten()
        if len(candidates):
            other[i] = candidates[torch.randint(len(candidates), (1,), generator=generator)]
    return other


def vision_skill(policy: DustPolicy, windows: Windows, buckets: int, seed: int, batch_size: int) -> dict:
    """The vision stream's error per tau bucket and of its joint sample, against the two trivial predictors."""
    batch, model = windows.batch, policy.model
    target = batch.get("future_tokens")
    valid = ~batch.get("future_is_clamped") if "future_is_clamped" in batch.keys() else torch.ones(
        len(target), dtype=torch.bool, device=target.device)
    mean_prediction = target[valid].mean(0, keepdim=True).expand_as(target)
    generator = torch.Generator().manual_seed(seed)
    errors = {name: [] for name in range(buckets)}
    with torch.no_grad():
        for rows in torch.arange(len(target)).split(batch_size):
            part = batch[rows.to(batch.device)]
            ctx = model.encode_context(part.get("state"), part.get("cond_tokens"), part.get("cond_mask", None))
            action, future = part.get("action_chunk"), part.get("future_tokens")
            for bucket in range(buckets):
                u = torch.rand(len(rows), generator=generator)
                tau = ((bucket + u) / buckets).to(future.device)
                eps_a = torch.randn(action.shape, generator=generator).to(action)
                eps_o = torch.randn(future.shape, generator=generator).to(future)
                noisy = interpolate(future, eps_o, tau)
                _, v_o = model(ctx, interpolate(action, eps_a, tau), noisy, tau, tau, need_action=False)
                estimate = noisy + (1 - tau).view(-1, 1, 1) * v_o
                errors[bucket].append(per_window_error(estimate, future))
    valid = valid.cpu()
    joint = per_window_error(own_samples(policy, batch, seed, batch_size)[1], target).cpu()
    present_error = per_window_error(windows.present, target).cpu()

    def row(error: Tensor, mask: Tensor = valid) -> dict:
        summary, present = (mean_interval(values[mask], windows.episode[mask]) for values in (error, present_error))
        return {**summary, "skill": 1 - summary["mean"] / present["mean"], "present_mean": present["mean"],
                "vs_present": paired(error[mask], present_error[mask], windows.episode[mask])}

    report = {"valid_windows": int(valid.sum()),
              "mean_predictor": mean_interval(per_window_error(mean_prediction, target).cpu()[valid],
                                              windows.episode[valid]),
              "present_predictor": mean_interval(present_error[valid], windows.episode[valid]),
              "buckets": [{"tau": [b / buckets, (b + 1) / buckets], **row(torch.cat(errors[b]).cpu())}
                          for b in range(buckets)],
              "joint_sample": row(joint)}
    if masks := windows.task_masks():  # a multi-task policy's world model may know one task and not another
        report["per_task"] = {name: {"joint_sample": row(joint, mask & valid)} for name, mask in masks.items()}
    return report


def own_samples(policy: DustPolicy, batch: TensorDict, seed: int, batch_size: int,
                source: SliceSource | None = None) -> tuple[Tensor, Tensor | None]:
    """Action chunks [N, H, Da] and the future [N, N_o, Dv] of the policy's sampler on ``batch``, each slice of
    ``batch_size`` seeded alike, so that every condition starts from the same action noise; ``source(part,
    rows)`` gives a slice's vision tokens per step (:data:`~dust_rl.agents.model.samplers.VisionSource`)."""
    schedule, actions, futures = schedule_for(policy.config), [], []
    for index, rows in enumerate(torch.arange(batch.batch_size[0]).split(batch_size)):
        part = batch[rows.to(batch.device)]
        generator = torch.Generator().manual_seed(seed * 100_003 + index)
        out = policy.model.predict_action(part, schedule, generator, noise_scale=policy.config.noise_scale,
                                          vision_source=None if source is None else source(part, rows))
        actions.append(out.get("action_chunk"))
        futures.append(out.get("future_tokens", None))
    return torch.cat(actions), (torch.cat(futures) if futures[0] is not None else None)


def renoised_source(future: Tensor | None, noise: Tensor) -> SliceSource:
    """The vision stream held at ``future`` [N, N_o, Dv] re-noised with ``noise`` to each step's tau_o, as the
    sampler's own future would stand at that flow time; None: at pure noise, tau_o = 0."""
    def for_slice(part: TensorDict, rows: Tensor) -> Callable[[DenoiseStep], tuple[Tensor, float]]:
        held = noise[rows.to(noise.device)]
        if future is None:
            return lambda step: (held, 0.0)
        target = future[rows.to(future.device)]
        return lambda step: (torch.lerp(held, target, step.tau_o), step.tau_o)
    return for_slice


def oracle_future(policy: DustPolicy, windows: Windows, seed: int, batch_size: int) -> dict:
    """Action error and action loss with the vision stream holding each of :data:`CONDITIONS`.

    The action loss holds the vision stream at the clean future (tau_o = 1; pure noise at tau_o = 0 for
    ``noise``); a variant with one timestep for both streams gets the future re-noised to the actions' tau and
    no ``noise`` condition (its model never sees the two at different flow times).
    """
    batch, model, cfg = windows.batch, policy.model, policy.config
    action, pad = batch.get("action_chunk"), batch.get("action_is_pad", None)
    device, valid = action.device, None if pad is None else ~pad
    skipped = {}
    conditions = list(CONDITIONS) if cfg.has_vision else ["own"]
    if cfg.has_vision and not cfg.decoupled:
        conditions.remove("noise")
        skipped["noise"] = f"variant {cfg.variant} shares one flow time between the streams"
    if "other" in conditions and not bool((windows.other >= 0).all()):
        conditions.remove("other")
        skipped["other"] = "fewer than two episodes of some diagnosed task"
    generator = torch.Generator().manual_seed(seed + 1)
    eps_o = torch.randn(batch.get("future_tokens").shape, generator=generator).to(action) if cfg.has_vision else None
    futures = {"true": batch.get("future_tokens"), "present": windows.present, "noise": eps_o}
    if "other" in conditions:
        futures["other"] = batch.get("future_tokens")[windows.other.to(device)]

    errors = {}
    for name in conditions:
        source = None if name == "own" else renoised_source(None if name == "noise" else futures[name], eps_o)
        chunks, sampled = own_samples(policy, batch, seed, batch_size, source)
        errors[name] = per_window_error(chunks, action, valid)
        if name == "own":
            futures["own"] = sampled
    loss_generator = torch.Generator().manual_seed(seed + 2)
    tau_a = sample_tau(len(action), s=cfg.tau_s, alpha=cfg.tau_alpha, generator=loss_generator).to(device)
    eps_a = torch.randn(action.shape, generator=loss_generator).to(action)
    noisy_action = interpolate(action, eps_a, tau_a)
    results = {}
    for name in conditions:
        losses = []
        with torch.no_grad():
            for rows in torch.arange(len(action), device=device).split(batch_size):
                part = batch[rows]
                ctx = model.encode_context(part.get("state"), part.get("cond_tokens"), part.get("cond_mask", None))
                vision = tau_o = None
                if cfg.has_vision:
                    vision, tau_o = futures[name][rows], torch.full((len(rows),), 0.0 if name == "noise" else 1.0,
                                                                     device=device)
                    if not cfg.decoupled:
                        tau_o = tau_a[rows]
                        vision = interpolate(vision, eps_o[rows], tau_o)
                v_a, _ = model(ctx, noisy_action[rows], vision, tau_a[rows], tau_o, need_vision=False)
                losses.append(per_window_error(v_a, velocity_target(action[rows], eps_a[rows]),
                                               None if valid is None else valid[rows]))
        results[name] = {"vision": CONDITIONS[name], "action_error": mean_interval(errors[name], windows.episode),
                         "action_loss": mean_interval(torch.cat(losses), windows.episode)}
    errors = {name: error.cpu() for name, error in errors.items()}

    def pairs(names: tuple[str, ...], mask: Tensor | slice = slice(None)) -> dict[str, dict]:
        return {name: paired(errors[a][mask], errors[b][mask], windows.episode[mask])
                for name, (a, b) in PAIRS.items() if name in names and a in errors and b in errors}

    report = {"conditions": results, "skipped": skipped, "paired_action_error": pairs(tuple(PAIRS))}
    if FUTURE_IS_CLAMPED_KEY in batch.keys():  # a clamped window's "true" future is its episode's last frame
        clamped = batch.get(FUTURE_IS_CLAMPED_KEY).cpu()
        report["by_window"] = {kind: {"windows": int(mask.sum()), "paired_action_error": pairs(READINGS, mask)}
                               for kind, mask in (("t+H inside the episode", ~clamped), ("clamped", clamped))
                               if mask.any()}
    if masks := windows.task_masks():
        report["per_task"] = {name: {"action_error": {condition: mean_interval(error[mask], windows.episode[mask])
                                                      for condition, error in errors.items()},
                                     "paired_action_error": pairs(READINGS, mask)} for name, mask in masks.items()}
    return report


def diagnose(config: WorldModelDiagnosis, command: str | None = None) -> dict:
    """Run both tests and write the report; returns what ``report.json`` holds.

    Raises:
        CheckpointError, DatasetError: an unreadable policy or dataset, or one that does not fit the other.
    """
    torch.set_num_threads(config.runtime.thread_count)
    policy = load_policy(config.policy).to(resolve_device(config.runtime.device)).eval()
    apply_sampling(policy, config.sampling, config.policy)
    trained_on = policy.info.get("dataset")
    if trained_on and pathlib.Path(trained_on).resolve() == config.dataset.resolve():
        raise DatasetError(f"{config.dataset} is the dataset {config.policy} was trained on; diagnose on held-out "
                           "episodes (e.g. dust-rl collect --seed 5000 ...)")
    features = dataset_features(config, policy)
    windows = windows_of(policy, features, config.windows, config.seed, config.batch_size)
    decoder, decoder_file = decoder_for(policy, config.policy, config.decoder)
    report = {"policy": str(config.policy), "dataset": str(config.dataset), "variant": policy.config.variant,
              "sampler": describe_sampler(resolved_sampler(policy)),
              "future_target": policy.config.future_target if policy.config.has_vision else None,
              "windows": windows.batch.batch_size[0], "command": command, "config": config_json(config),
              "oracle_future": oracle_future(policy, windows, config.seed, config.batch_size)}
    if policy.config.has_vision:
        report["vision_stream"] = vision_skill(policy, windows, config.tau_buckets, config.seed, config.batch_size)
    config.out.mkdir(parents=True, exist_ok=True)
    report["futures"] = None if decoder is None else {
        "figure": str(config.out / "futures.png"), "token_decoder": None if decoder_file is None else str(decoder_file)}
    if decoder is not None:
        with atomic_write(config.out / "futures.png", "wb") as f:
            futures_figure(policy, features, decoder, config.seed).save(f, format="PNG")
    write_json_atomic(config.out / "report.json", report)
    write_text_atomic(config.out / "report.md", markdown(report))
    plot(report, config.out / "world_model.png")
    return report


def _interval(row: dict, digits: int = 4) -> str:
    return f"{row['mean']:.{digits}f} [{row['ci95_low']:.{digits}f}, {row['ci95_high']:.{digits}f}]"


def markdown(report: dict) -> str:
    """The report's tables."""
    sampler = report["sampler"]
    lines = [f"# World-model diagnosis of {report['policy']}", "",
             f"{report['windows']} windows of {report['dataset']}; variant {report['variant']}; sampler "
             f"{sampler['name']} (N_A {sampler['n_action_steps']}, N_o {sampler['vision_steps']}); means over episodes "
             "with 95% intervals over episodes; command: "
             f"`{report['command']}`", ""]
    vision = report.get("vision_stream")
    if vision:
        lines += ["## The vision stream against trivial predictors", "",
                  f"Target: {report['future_target']}; {vision['valid_windows']} windows whose t+H is inside the "
                  f"episode. Error of the targets' mean: {_interval(vision['mean_predictor'])}; of the present "
                  f"frame: {_interval(vision['present_predictor'])}.", "",
                  "| tau_o | error (95% CI) | skill (1 - err / err_present) |", "|---|---|---|"]
        for row in vision["buckets"]:
            lines.append(f"| {row['tau'][0]:.2f}-{row['tau'][1]:.2f} | {_interval(row)} | {row['skill']:+.3f} |")
        lines += [f"| joint sample (the policy's sampler) | {_interval(vision['joint_sample'])} | "
                  f"{vision['joint_sample']['skill']:+.3f} |", ""]
    oracle = report["oracle_future"]
    lines += ["## The oracle-future test", "",
              "| vision stream holds | action error vs demonstration (95% CI) | action loss (95% CI) |",
              "|---|---|---|"]
    for row in oracle["conditions"].values():
        lines.append(f"| {row['vision']} | {_interval(row['action_error'])} | {_interval(row['action_loss'])} |")
    if oracle["paired_action_error"]:
        lines += ["", "| action error, paired | difference (95% CI) | p |", "|---|---|---|"]
        for name, row in oracle["paired_action_error"].items():
            lines.append(f"| {name} | {_interval(row)} | {row['p']:.3g} |")
    if oracle.get("by_window"):
        lines += ["", "Windows whose t+H lies inside the episode apart from the clamped ones (whose true future is "
                  "the episode's last frame):", "", "| windows | count | " + " | ".join(READINGS) + " |",
                  "|---|---|" + "---|" * len(READINGS)]
        for kind, row in oracle["by_window"].items():
            pairs = row["paired_action_error"]
            lines.append(f"| {kind} | {row['windows']} | " + " | ".join(
                f"{pairs[name]['mean']:+.4f} (p {pairs[name]['p']:.3g})" if name in pairs else "-"
                for name in READINGS) + " |")
    lines += [""] * bool(oracle["skipped"]) + [f"Condition '{name}' not run: {why}."
                                               for name, why in oracle["skipped"].items()]
    return "\n".join(lines + _per_task_lines(report)) + "\n"


def _per_task_lines(report: dict) -> list[str]:
    """The readings of both tests per task, for a dataset of several tasks (none otherwise)."""
    oracle, vision = report["oracle_future"].get("per_task"), (report.get("vision_stream") or {}).get("per_task")
    if not oracle:
        return []
    readings = [name for name in READINGS if name in next(iter(oracle.values()))["paired_action_error"]]
    columns = ["task", "windows", "own action error", *(f"{name} (p)" for name in readings),
               *(["windows with t+H inside", "present-frame error", "joint-sample error", "skill"] if vision else [])]
    lines = ["", "## Per task", "", "Action error of the policy's own sample and the paired readings (p)"
             + ("; the world model's joint sample against the present frame." if vision else "."), "",
             "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for task, row in oracle.items():
        own, pairs = row["action_error"]["own"], row["paired_action_error"]
        cells = [task, str(own["windows"]), f"{own['mean']:.4f}",
                 *(f"{pairs[name]['mean']:+.4f} ({pairs[name]['p']:.3g})" for name in readings)]
        if vision:
            world = vision[task]["joint_sample"]
            cells += [str(world["windows"]), f"{world['present_mean']:.4f}", f"{world['mean']:.4f}",
                      f"{world['skill']:+.3f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def plot(report: dict, path: pathlib.Path) -> None:
    """Vision error per tau bucket against the predictors (left); each condition's action error minus that with
    pure noise, paired (right; the plain errors for a policy without a vision stream)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(10, 4), layout="constrained")
    left, right = figure.subplots(1, 2)
    vision = report.get("vision_stream")
    if vision:
        centres = [sum(row["tau"]) / 2 for row in vision["buckets"]]
        left.errorbar(centres, [row["mean"] for row in vision["buckets"]],
                      yerr=[row["mean"] - row["ci95_low"] for row in vision["buckets"]], marker="o",
                      label="vision stream, one step")
        for name, style in (("mean_predictor", ":"), ("present_predictor", "--")):
            left.axhline(vision[name]["mean"], linestyle=style, color="grey", label=name.replace("_", " "))
        left.axhline(vision["joint_sample"]["mean"], color="C1", label="joint sample")
        left.set(xlabel="tau_o", ylabel="error of the future (standardised)", title="world model")
        left.legend(fontsize=8)
    else:
        left.set_axis_off()
        left.text(0.5, 0.5, "no vision stream", ha="center")
    oracle = report["oracle_future"]
    pairs = {name: row for name, row in oracle["paired_action_error"].items() if name.endswith(" - noise")}
    rows = pairs or {name: row["action_error"] for name, row in oracle["conditions"].items()}
    right.bar(list(rows), [row["mean"] for row in rows.values()],
              yerr=[row["mean"] - row["ci95_low"] for row in rows.values()], color=[f"C{i}" for i in range(len(rows))])
    right.axhline(0.0, color="black", linewidth=0.8)
    right.set(ylabel="action error, paired difference" if pairs else "action error vs demonstration",
              title="oracle-future test" + (" (below 0: the future helps)" if pairs else ""))
    with atomic_write(path, "wb") as f:
        figure.savefig(f, format="png", dpi=100)


def diagnose_world_model_command(config: WorldModelDiagnosis, command: str | None = None) -> None:
    """``dust-rl diagnose world-model``: run, print the tables, say where the files are."""
    report = diagnose(config, command)
    print((config.out / "report.md").read_text())
    futures = f"; predicted futures: {report['futures']['figure']}" if report["futures"] else ""
    print(f"report: {config.out / 'report.json'}; plot: {config.out / 'world_model.png'}{futures}")
