"""The learnability gate of noise steering: can what the policy sees rank its own chunks as the simulator does?

Why: noise steering (``dust-rl finetune steer``) can only help if a critic learns, from the actor's inputs, which of
the chunks the base policy might sample leads further. Before a long RL run this asks the same of a plain
regression, with the simulator as teacher: at every plan of the base policy K candidate chunks are sampled (K
initial noises), each one's executed part is played from a snapshot of the simulator (``DustEnv.snapshot`` /
``restore``), and the task progress it lands at (the dense reward's potential, 1 at success) is its label. Scorers
are fitted to rank the K candidates from

- deployable features: the robot state, the policy's read-out estimate of the objects (in metres), the chunk's
  planned end point (the executed translations summed, in delta control) relative to each object, its gripper
  command, and the executed actions themselves;
- privileged features: the same with the simulator's true object positions in place of the estimate;

a linear scorer and a small MLP each (early stopping), on episodes split three ways (fit / selection / report).
The report gives the mean within-plan Spearman correlation with the simulator's ranking on the report episodes,
and the progress a scorer's pick gains over the first candidate (the base's own draw) against the simulator's
pick. Then best-of-K closed loop on the validation seeds: the base (candidate 0, the policy's own distribution),
the deployable scorer's pick, the privileged scorer's pick and the simulator's pick (one chunk ahead: the ceiling
any one-chunk chooser among K draws can reach), all on the same seeds and the same candidate draws, paired
McNemar tests against the base.

Every phase is resumable (one file per collected episode, one line per closed-loop episode), outside the package:

    .venv/bin/python experiments/learnability_gate.py --policy runs/gate/push_base/policy.pt --out runs/gate/push \
        [--candidates 8] [--episodes 300] [--train-seed 20000] [--eval-episodes 100] [--eval-seed 5000]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib

import numpy as np
import torch
from scipy.stats import spearmanr
from tqdm import tqdm

from dust_rl.agents import DustPolicy, load_policy
from dust_rl.data.env_state_norm import EnvStateNorm
from dust_rl.envs.env import MAX_TRANSLATION
from dust_rl.envs.factory import make_env
from dust_rl.evaluate.records import mcnemar, wilson_interval
from dust_rl.rl.frozen_policy_env import observe_batch
from dust_rl.rl.steering import NoiseSteeringEnv

EE_POSITION, EE_OPENING = slice(-8, -5), -1  # the robot state ends with the gripper's position, quaternion, opening
NOISE_OFFSET = 1_000_003  # the candidates' noise stream of an episode: its seed plus this (far from every schedule)
NOISE_BOUND = 4.0  # latents of +-1 map to +-4: the N(0, 1) candidate noise is clipped at 4 standard deviations
SPLITS = (0.6, 0.2)  # of the collected episodes: fit, selection; the rest is the report split
KINDS = ("deployable", "privileged")  # the feature sets scorers are fitted on
ARMS = ("base", *KINDS, "simulator")


class GateEnv:
    """The base policy in a steering env, with K candidate chunks per plan and the simulator's label of each."""

    def __init__(self, policy: DustPolicy, candidates: int) -> None:
        task = policy.info["tasks"][0]
        kwargs = {k: v for k, v in policy.info.get("env_kwargs", {}).items() if k != "task"}
        self.env = NoiseSteeringEnv(make_env(policy.info["env_id"], {**kwargs, "task": task}), policy,
                                    noise_bound=NOISE_BOUND)
        self.sim = self.env.env.unwrapped
        self.policy, self.candidates = policy, candidates
        self.norm = EnvStateNorm.of_policy(policy)
        self.task_index = self.norm.task_indices([task])
        self.objects = self.sim.task.environment_state_dim // 3  # xyz triples of the object state

    def reset(self, seed: int) -> dict:
        self.noise = torch.Generator().manual_seed(seed + NOISE_OFFSET)
        return self.env.reset(seed=seed)[0]

    def plan(self) -> torch.Tensor:
        """K candidate chunks [K, H, Da] (env units) for the newest observation, candidate 0 first."""
        latents = (torch.randn(self.candidates, self.env.steering.action_dim, generator=self.noise)
                   / NOISE_BOUND).clamp(-1, 1).numpy()
        features = torch.cat([self.env.features] * self.candidates)
        return self.env.steering.plan(self.policy, features, latents, self.env.generator).get("action_chunk").cpu()

    def labels(self, chunks: torch.Tensor) -> np.ndarray:
        """Each candidate's progress [K] after its executed part, played from a snapshot (1: success)."""
        snapshot, out = self.sim.snapshot(), []
        for chunk in chunks:
            success = False
            for action in chunk[:self.env.execute_steps].numpy():
                _, success, truncated, _ = self.sim.step_unobserved(action)
                if success or truncated:
                    break
            out.append(1.0 if success else self.sim.progress())
            self.sim.restore(snapshot)
        return np.array(out)

    def features(self, view: dict, chunks: torch.Tensor, kinds: tuple[str, ...] = KINDS) -> dict[str, np.ndarray]:
        """Per candidate [K, F], the features of each of ``kinds`` (module doc)."""
        objects = {"deployable": lambda: self.norm.denormalize(self.policy.estimate_env_state(self.env.features),
                                                               self.task_index)[0].numpy(),
                   "privileged": lambda: self.sim.task.environment_state(self.sim.data)}
        return {kind: self._features(view["robot_state"], objects[kind](), chunks) for kind in kinds}

    def _features(self, robot: np.ndarray, objects: np.ndarray, chunks: torch.Tensor) -> np.ndarray:
        executed = chunks[:, :self.env.execute_steps].clamp(-1, 1).numpy().astype(np.float64)
        ee = robot[EE_POSITION]
        end = ee + executed[:, :, :3].sum(1) * MAX_TRANSLATION
        xyz = objects[:3 * self.objects].reshape(self.objects, 3)
        k = len(chunks)
        context = np.broadcast_to(np.r_[robot[EE_POSITION], robot[EE_OPENING], xyz.ravel()], (k, 3 + 1 + xyz.size))
        to_objects = (end[:, None, :2] - xyz[None, :, :2])
        return np.concatenate([context, end - ee, to_objects.reshape(k, -1), np.linalg.norm(to_objects, axis=-1),
                               executed[:, :, -1].mean(1, keepdims=True), executed.reshape(k, -1)], axis=1)

    def execute(self, chunk: torch.Tensor) -> tuple[dict, bool, bool]:
        """Execute ``chunk``'s executed part; the next view, whether the episode ended, and whether it succeeded."""
        obs, _, terminated, truncated, info = self.env.execute(chunk)
        return observe_batch([self.env], [obs])[0], terminated or truncated, bool(info.get("is_success"))


def collect(gate: GateEnv, folder: pathlib.Path, seeds: range) -> None:
    """One ``.npz`` per episode of the base (candidate 0 executed): per plan the K candidates' features and labels."""
    folder.mkdir(parents=True, exist_ok=True)
    for seed in tqdm(seeds, desc="collect"):
        path = folder / f"episode-{seed}.npz"
        if path.exists():
            continue
        view, done, rows = gate.reset(seed), False, {"deployable": [], "privileged": [], "label": []}
        while not done:
            chunks = gate.plan()
            for name, values in gate.features(view, chunks).items():
                rows[name].append(values)
            rows["label"].append(gate.labels(chunks))
            view, done, _ = gate.execute(chunks[0])
        tmp = folder / f".{path.name}"  # outside the episode-*.npz glob until whole
        np.savez(tmp, **{name: np.stack(values) for name, values in rows.items()})
        os.replace(tmp, path)


class Scorer(torch.nn.Module):
    """A linear map or a two-layer MLP of standardised features to a candidate's score."""

    def __init__(self, mean: np.ndarray, std: np.ndarray, hidden: int | None) -> None:
        super().__init__()
        width = len(mean)
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32))
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32))
        self.net = (torch.nn.Linear(width, 1) if hidden is None else torch.nn.Sequential(
            torch.nn.Linear(width, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, hidden), torch.nn.ReLU(),
            torch.nn.Linear(hidden, 1)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [..., F] -> [...]
        return self.net((x - self.mean) / self.std).squeeze(-1)


def centred_loss(scores: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Squared error of the scores' within-plan deviations against the labels' ([P, K]): a ranking, not a level."""
    return ((scores - scores.mean(1, keepdim=True)) - (labels - labels.mean(1, keepdim=True))).square().mean()


def mean_spearman(scores: np.ndarray, labels: np.ndarray) -> float:
    """The mean over plans ([P, K]) of the scores' Spearman correlation with the labels (plans of tied labels
    skipped: nothing to rank)."""
    values = [spearmanr(s, y).statistic for s, y in zip(scores, labels, strict=True) if np.ptp(y) > 1e-9]
    return float(np.nanmean(values)) if values else float("nan")


def fit(x: dict[str, np.ndarray], y: dict[str, np.ndarray], hidden: int | None, weight_decay: float,
        seed: int = 0, steps: int = 4000, patience: int = 500) -> tuple[Scorer, float]:
    """A scorer fitted on ``x["fit"]`` ([P, K, F]), stopped early at its best selection-split Spearman."""
    torch.manual_seed(seed)
    flat = x["fit"].reshape(-1, x["fit"].shape[-1])
    scorer = Scorer(flat.mean(0), flat.std(0) + 1e-6, hidden)
    optimiser = torch.optim.AdamW(scorer.parameters(), lr=1e-3, weight_decay=weight_decay)
    xs, ys = torch.as_tensor(x["fit"], dtype=torch.float32), torch.as_tensor(y["fit"], dtype=torch.float32)
    selection = torch.as_tensor(x["selection"], dtype=torch.float32)
    generator = torch.Generator().manual_seed(seed)
    best, best_state, since = -math.inf, None, 0
    for step in range(steps):
        batch = torch.randint(len(xs), (256,), generator=generator)
        loss = centred_loss(scorer(xs[batch]), ys[batch])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % 50 == 49:
            with torch.no_grad():
                score = mean_spearman(scorer(selection).numpy(), y["selection"])
            if score > best:
                best, best_state, since = score, {k: v.clone() for k, v in scorer.state_dict().items()}, 0
            elif (since := since + 50) >= patience:
                break
    if best_state is not None:  # None: no selection plan had untied labels to rank; the last weights stand
        scorer.load_state_dict(best_state)
    return scorer.eval(), best


def fit_scorers(folder: pathlib.Path, out: pathlib.Path) -> dict:
    """Ridge and MLP scorers per feature set (the best on the selection split kept), their report-split figures."""
    episodes = sorted(folder.glob("episode-*.npz"), key=lambda p: int(p.stem.split("-")[1]))
    if len(episodes) < 5:
        raise SystemExit(f"{folder}: {len(episodes)} collected episodes; collect more first")
    cut = [round(len(episodes) * SPLITS[0]), round(len(episodes) * sum(SPLITS))]
    parts = {"fit": episodes[:cut[0]], "selection": episodes[cut[0]:cut[1]], "report": episodes[cut[1]:]}
    data = {name: [np.load(p, allow_pickle=False) for p in paths] for name, paths in parts.items()}
    labels = {name: np.concatenate([d["label"] for d in files]) for name, files in data.items()}
    result = {"plans": {name: len(v) for name, v in labels.items()}, "episodes": {k: len(v) for k, v in parts.items()}}
    report = labels["report"]
    result["report_progress_gain"] = {"simulator": float((report.max(1) - report[:, 0]).mean())}
    for kind in KINDS:
        x = {name: np.concatenate([d[kind] for d in files]) for name, files in data.items()}
        fitted = [(f"{model} wd {wd}", *fit(x, labels, hidden, wd))
                  for model, hidden in (("linear", None), ("mlp", 128)) for wd in (1e-4, 1e-2)]
        rows = {}
        for name, scorer, selection in fitted:
            with torch.no_grad():
                scores = scorer(torch.as_tensor(x["report"], dtype=torch.float32)).numpy()
            picked = report[np.arange(len(report)), scores.argmax(1)]
            rows[name] = {"selection_spearman": selection, "report_spearman": mean_spearman(scores, report),
                          "report_progress_gain": float((picked - report[:, 0]).mean())}
        best_name, best, _ = max(fitted, key=lambda row: row[2])
        torch.save(best.state_dict(), out / f"scorer-{kind}.pt")
        result[kind] = {"scorers": rows, "chosen": best_name, "hidden": None if best_name.startswith("linear") else 128,
                        "width": x["fit"].shape[-1]}
    (out / "fit.json").write_text(json.dumps(result, indent=1))
    return result


def load_scorer(out: pathlib.Path, kind: str, fitted: dict) -> Scorer:
    """The chosen scorer of feature set ``kind`` as :func:`fit_scorers` saved it (its statistics are buffers)."""
    row = fitted[kind]
    scorer = Scorer(np.zeros(row["width"]), np.ones(row["width"]), row["hidden"])
    scorer.load_state_dict(torch.load(out / f"scorer-{kind}.pt", weights_only=True))
    return scorer.eval()


def closed_loop(gate: GateEnv, arm: str, scorer: Scorer | None, seeds: range, path: pathlib.Path) -> dict[int, bool]:
    """Success per seed of best-of-K by ``arm``, one JSON line per finished episode (resumed from ``path``)."""
    done = {}
    if path.exists():
        done = {row["seed"]: row["success"] for row in map(json.loads, path.read_text().splitlines())}
    for seed in tqdm([s for s in seeds if s not in done], desc=arm):
        view, over, success = gate.reset(seed), False, False
        while not over:
            chunks = gate.plan()
            if arm == "base":
                index = 0
            elif arm == "simulator":
                index = int(gate.labels(chunks).argmax())
            else:
                with torch.no_grad():
                    x = torch.as_tensor(gate.features(view, chunks, (arm,))[arm], dtype=torch.float32)
                    index = int(scorer(x).argmax())
            view, over, success = gate.execute(chunks[index])
        with path.open("a") as file:
            file.write(json.dumps({"seed": seed, "success": success}) + "\n")
        done[seed] = success
    return {s: done[s] for s in seeds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", type=pathlib.Path, required=True)
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--candidates", type=int, default=8, help="K chunks sampled per plan")
    parser.add_argument("--episodes", type=int, default=300, help="episodes of the base to collect")
    parser.add_argument("--train-seed", type=int, default=20000, help="first seed of the collected episodes")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--eval-seed", type=int, default=5000, help="first closed-loop seed (validation)")
    parser.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS))
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    policy = load_policy(args.policy).eval()
    if not policy.config.aux_state_dim:
        raise SystemExit("the deployable features need a policy with a state read-out (--model.lambda-aux)")
    args.out.mkdir(parents=True, exist_ok=True)
    gate = GateEnv(policy, args.candidates)
    with torch.inference_mode():
        collect(gate, args.out / "collected", range(args.train_seed, args.train_seed + args.episodes))
    fitted = fit_scorers(args.out / "collected", args.out)
    seeds = range(args.eval_seed, args.eval_seed + args.eval_episodes)
    outcomes = {}
    with torch.inference_mode():
        for arm in args.arms:
            scorer = load_scorer(args.out, arm, fitted) if arm in fitted else None
            outcomes[arm] = closed_loop(gate, arm, scorer, seeds, args.out / f"closed-loop-{arm}.jsonl")
    lines = ["| scorer | features | selection Spearman | report Spearman | progress gain over candidate 0 |",
             "|---|---|---|---|---|"]
    for kind in KINDS:
        for name, row in fitted[kind]["scorers"].items():
            chosen = " (chosen)" if name == fitted[kind]["chosen"] else ""
            lines.append(f"| {name}{chosen} | {kind} | {row['selection_spearman']:.3f} | {row['report_spearman']:.3f}"
                         f" | {row['report_progress_gain']:+.4f} |")
    lines.append(f"| simulator | | | 1 | {fitted['report_progress_gain']['simulator']:+.4f} |")
    lines += ["", f"| best of {args.candidates} by | success (seeds {seeds.start}..{seeds.stop - 1}) | 95% CI | "
              "vs base: won / lost | McNemar p |", "|---|---|---|---|---|"]
    summary = {"fit": fitted, "closed_loop": {}}
    for arm, results in outcomes.items():
        wins = sum(results.values())
        low, high = wilson_interval(wins, len(results))
        base = outcomes.get("base", results)
        test = mcnemar(results, base)
        summary["closed_loop"][arm] = {"successes": wins, "episodes": len(results), **test}
        lines.append(f"| {arm} | {wins / len(results):.0%} ({wins}/{len(results)}) | {low:.0%}-{high:.0%} | "
                     f"{test['gained']} / {test['lost']} | {test['p_value']:.3f} |")
    (args.out / "report.json").write_text(json.dumps(summary, indent=1))
    (args.out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
