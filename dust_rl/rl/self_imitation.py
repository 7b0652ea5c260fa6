"""Success-filtered self-imitation: ``dust-rl finetune self-imitation``.

Why: an imitation policy trained on 200 demonstrations has seen 200 layouts, and most of its failures are
layouts it has not learnt to read (docs/franka_results.md, "The token read-out"); noise steering and a residual could
not move it (BENCHMARKS.md, "RL fine-tuning"): its samples hardly differ, and a sparse reward gives a critic
little to fit. Its own successes on fresh layouts are demonstrations it can reproduce, labelled by the
reward alone. Each round rolls the current policy out on fresh seeds until it has ``rollout_successes``
successes (``dust-rl collect --policy``: the episodes ``dust-rl eval`` would run on those seeds), then
fine-tunes it on its demonstrations plus those successes with their executed actions (``dust-rl train
--init-policy --data.extra-dataset``): a policy-improvement step on the binary reward (filtered behaviour cloning,
as in RoboCat's self-improvement loop), which changes the weights, not how the policy is sampled.

``--train.data.extra-action-key expert_action`` turns it into DAgger (Ross et al., 2011), the reference with a
teacher: every rollout is kept, failures included (there the expert's correction matters most), and the
scripted expert's label at each visited state is taught instead of the executed action. It needs the
privileged expert, so it measures how much of the gap a reward alone closes.

The run folder holds one cached job per stage, so rerunning the command resumes where it stopped:
``round-<r>/rollouts/`` (a dataset), ``round-<r>/train/`` (a training run whose ``policy.pt`` is the next
round's policy), ``curve/round-<r>/`` (its validation episodes, for ``learning_curve.png``) and
``eval/base/`` and ``eval/round-<r>/`` (the held-out comparison), so resuming with more rounds extends a run.
The control (``--no-control`` skips it) is the base policy fine-tuned for as many steps on its demonstrations alone,
``control/steps-<n>/`` and ``eval/control-steps-<n>/``: a base stopped before it fitted its demonstrations gains from
the extra steps whatever the rollouts (push: 56% -> 68% held-out, more than any rollouts gave), so a method is
credited only with what it adds above that row.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time

from dust_rl.data import collect_demos
from dust_rl.data.episodes import scan_episodes
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate
from dust_rl.evaluate.report import plot_learning_curve
from dust_rl.rl.config import SelfImitationConfig, is_dagger
from dust_rl.rl.report_rows import BASE_ROW
from dust_rl.storage.atomic_files import write_json_atomic
from dust_rl.train.imitation import TrainConfig, train

# Round r rolls out from seed rollout_seed + r * ROUND_SEEDS: rounds never share a layout.
ROUND_SEEDS = 10_000
ROUND_SECONDS = "seconds.json"  # in each round's folder: its collecting and fine-tuning time


def self_imitation(config: SelfImitationConfig, task: str, env_id: str, env_kwargs: dict) -> dict:
    """Run (or resume) every round, then evaluate the base, the control (``config.control``: the base fine-tuned as
    long on its demonstrations alone) and the last round's policy on the held-out seeds; returns the report's parts."""
    dagger = is_dagger(config.train.data.extra_action_key)
    name = "DAgger" if dagger else "self_imitation"
    policy, curve, rounds = config.policy, [_curve_point(config, config.policy, "round-0", 0)], []
    for r in range(config.rounds):
        began, folder = time.perf_counter(), config.out / f"round-{r + 1}"
        rollouts = folder / "rollouts"
        collect_demos(rollouts, env_id, [task], config.rollout_successes, env_kwargs=env_kwargs,
                      start_seed=config.rollout_seed + r * ROUND_SEEDS, keep_failed=dagger, policy=policy,
                      policy_runtime=config.runtime, progress=config.runtime.progress)
        records = scan_episodes(rollouts)[task].values()
        policy = _fine_tune(config, policy, rollouts, folder / "train")
        rounds.append({"policy": str(policy), "rollouts": len(records), "successes": sum(r.success for r in records),
                       "env_steps": sum(r.length for r in records),
                       "seconds": _add_seconds(folder, time.perf_counter() - began)})
        env_steps = sum(row["env_steps"] for row in rounds)
        curve.append(_curve_point(config, policy, f"round-{r + 1}", env_steps))
        last_seed = config.curve_seed + config.curve_episodes - 1
        plot_learning_curve(curve, config.out / "learning_curve.png",
                            f"{name}, seeds {config.curve_seed}..{last_seed}")
    trained_s = sum(row["seconds"] for row in rounds)
    rows = {BASE_ROW: _evaluate(config, config.policy, config.out / "eval" / "base")}
    if config.control:
        name_of_control, rows[name_of_control] = control_row(config)
    rows[f"{name} ({config.rounds} rounds)"] = _evaluate(config, policy, config.out / "eval" / f"round-{config.rounds}")
    return {"rows": rows, "train_seconds": trained_s, "rollout_env_steps": sum(r["env_steps"] for r in rounds),
            "rounds": rounds, "curve": curve, "policy_file": str(policy)}


def _add_seconds(folder: pathlib.Path, seconds: float) -> float:
    """The round's wall time collecting and fine-tuning, summed over every invocation that worked on it (so a
    resumed run reports the whole, not the seconds it took to read the cached stages back)."""
    path = folder / ROUND_SECONDS
    total = (json.loads(path.read_text())["seconds"] if path.is_file() else 0.0) + seconds
    write_json_atomic(path, {"seconds": total})
    return total


def control_row(config: SelfImitationConfig) -> tuple[str, dict]:
    """The base policy fine-tuned on its demonstrations alone, for as many steps as all rounds together, and its row
    on the held-out seeds (both cached in the run folder, by step count: a run resumed with more rounds gets its own
    control)."""
    steps = config.rounds * config.train.optim.steps
    longer = dataclasses.replace(config.train, optim=dataclasses.replace(config.train.optim, steps=steps))
    policy = _fine_tune(dataclasses.replace(config, train=longer),
                        config.policy, None, config.out / "control" / f"steps-{steps}")
    row = _evaluate(config, policy, config.out / "eval" / f"control-steps-{steps}")
    return f"demonstrations alone ({steps} steps, the control)", row


def _fine_tune(config: SelfImitationConfig, policy: pathlib.Path, rollouts: pathlib.Path | None,
               out: pathlib.Path) -> pathlib.Path:
    """``policy`` trained further on its demonstrations and ``rollouts`` (none: the demonstrations alone); a
    finished run is not trained again."""
    if not (out / "policy.pt").is_file():
        rounds = config.train
        settings = rounds.under(config.runtime, init_policy=policy, seed=config.seed,
                                data=dataclasses.replace(rounds.data, extra_dataset=rollouts))
        resume = (out / "config.json").is_file()
        train(TrainConfig.from_settings(settings, dataset=config.demos, out=out, resume=resume))
    return out / "policy.pt"


def _curve_point(config: SelfImitationConfig, policy: pathlib.Path, name: str, env_steps: int) -> dict:
    """Success of ``policy`` on the validation seeds, at ``env_steps`` env steps of rollouts."""
    report = _report(config, policy, config.out / "curve" / name, config.curve_episodes, config.curve_seed, 0)
    return {"round": name, "env_steps": env_steps, **report["overall"]}


def _evaluate(config: SelfImitationConfig, policy: pathlib.Path, out: pathlib.Path) -> dict:
    """``policy``'s row on the held-out seeds, as ``dust-rl eval`` reports it."""
    return _report(config, policy, out, config.eval_episodes, config.eval_seed, 1)["tasks"][0]


def _report(config: SelfImitationConfig, policy: pathlib.Path, out: pathlib.Path, episodes: int, seed: int,
            videos: int) -> dict:
    """The evaluation report of ``policy`` in ``out``: read back if that evaluation already ran."""
    if (out / "report.json").is_file():
        return json.loads((out / "report.json").read_text())
    return evaluate(EvalConfig(policy=policy, out=out, episodes=episodes, seed=seed, workers=1, videos=videos,
                               max_steps=config.max_steps, runtime=config.runtime))
