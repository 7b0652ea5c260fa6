"""Evaluation report files: JSON, markdown, a success-rate bar plot, and training loss curves.

Every function takes plain data (the report dict of :func:`dust_rl.evaluate.closed_loop.evaluate`, or a folder of
CSV logs) and writes files, each atomically; nothing here runs a policy. Plots draw on a bare matplotlib
``Figure`` (Agg canvas), so they never touch pyplot's global state or need a display.
"""

from __future__ import annotations

import csv
import os
import pathlib

from matplotlib.figure import Figure

from dust_rl.storage.atomic_files import atomic_write, write_json_atomic, write_text_atomic

REPORT_JSON = "report.json"
REPORT_MD = "report.md"
SUCCESS_PNG = "success.png"


def write_report(report: dict, out_dir: pathlib.Path) -> dict[str, pathlib.Path]:
    """Write ``report.json``, ``report.md`` and ``success.png`` into ``out_dir``; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / REPORT_JSON, "markdown": out_dir / REPORT_MD, "success_plot": out_dir / SUCCESS_PNG}
    write_json_atomic(paths["json"], report, indent=2)
    write_text_atomic(paths["markdown"], markdown_report(report, out_dir))
    plot_success(report["tasks"], paths["success_plot"])
    return paths


def percent(rate: float) -> str:
    return f"{100 * rate:.0f}%"


def table_row(row: dict) -> str:
    """``| task | episodes | success | 95% CI | mean length |`` of one summary row."""
    return (f"| {row['task']} | {row['episodes']} | {percent(row['success_rate'])} ({row['successes']}/"
            f"{row['episodes']}) | {percent(row['ci95_low'])}-{percent(row['ci95_high'])} | {row['mean_length']:.1f} |")


def rl_agent_line(about: dict | None) -> list[str]:
    """The report's line on an RL agent acting through the policy (none without one)."""
    if about is None:
        return []
    return [f"- acting through a fine-tuned RL agent: `{about['method']}` with {about['algorithm']} "
            f"({about['parameters'] / 1e6:.2f}M parameters), {about['steps']} RL steps on `{about['task']}`; the "
            "imitation policy frozen"]


def markdown_report(report: dict, out_dir: pathlib.Path) -> str:
    """The report as markdown: setting, per-task table with the overall row, plots and video links.

    Links are relative to ``out_dir`` (where the markdown file lives), so the folder can be moved.
    """
    sampler = report["sampler"]
    lines = [
        f"# Evaluation: {report['policy']}",
        "",
        f"- policy: `{report['policy']}` (variant `{report['variant']}`, "
        f"{report.get('trainable_parameters', 0) / 1e6:.2f}M trainable parameters)",
        *rl_agent_line(report.get("rl_agent")),
        f"- env: `{report['env_id']}` {report['env_kwargs']}",
        f"- sampler: {sampler['name']}, N_A = {sampler['n_action_steps']}, N_o = {sampler['vision_steps']}"
        f", initial noise x{sampler.get('noise_scale', 1.0):g}; "
        f"{report.get('execute_steps', '?')} actions executed "
        "per chunk",
        f"- seeds {report['seeds'][0]}..{report['seeds'][1]} per task; {report['noise_seeding']}",
        f"- {report['env_steps']} env steps in {report['episodes_time_s']:.1f} s "
        f"({report['env_steps_per_s']:.1f} steps/s with {report['config']['workers']} env processes) "
        f"after {report['startup_s']:.1f} s of start-up; wall time {report['wall_time_s']:.1f} s",
    ]
    if report.get("command"):
        lines.append(f"- command: `{report['command']}`")
    lines += ["", "| task | episodes | success | 95% CI | mean length |", "|---|---|---|---|---|"]
    lines += [table_row(row) for row in report["tasks"]]
    lines += [table_row({**report["overall"], "task": "**overall**"}), "", f"![success rate]({SUCCESS_PNG})"]
    if report.get("loss_plot"):
        lines.append(f"![training loss]({os.path.relpath(report['loss_plot'], out_dir)})")
    videos = [(row["task"], video) for row in report["tasks"] for video in row["videos"]]
    if videos:
        lines += ["", "Rollouts (camera views, then the decoded predicted future beside the real one when the "
                  "policy has a decoder):", ""]
        lines += [f"- {task} seed {v['seed']}: [{pathlib.Path(v['path']).name}]({os.path.relpath(v['path'], out_dir)}) "
                  f"({'success' if v['success'] else 'failure'}, {v['length']} steps)" for task, v in videos]
    return "\n".join(lines) + "\n"


def plot_success(rows: list[dict], out_png: pathlib.Path) -> pathlib.Path:
    """Bar chart of per-task success rates with their 95% intervals as error bars."""
    fig = Figure(figsize=(max(4.0, 0.9 * len(rows) + 1.5), 3.5), layout="constrained")
    ax = fig.add_subplot()
    rates = [row["success_rate"] for row in rows]
    errors = [[rate - row["ci95_low"] for rate, row in zip(rates, rows)],
              [row["ci95_high"] - rate for rate, row in zip(rates, rows)]]
    ax.bar(range(len(rows)), rates, yerr=errors, capsize=4, color="tab:blue", ecolor="black")
    ax.set_xticks(range(len(rows)), [f"{row['task']}\n(n={row['episodes']})" for row in rows], rotation=30, ha="right")
    ax.set_ylim(0, 1)
    ax.set_ylabel("success rate (95% CI)")
    save_png(fig, out_png)
    return out_png


def read_scalar_csv(path: pathlib.Path) -> tuple[list[int], list[float]]:
    """Steps and values of a torchrl ``CSVLogger`` scalar file (``step,value`` rows, no header).

    A resumed run logs some steps again: the last value of each step wins. Rows that do not parse
    (a line cut by a killed writer) are skipped.
    """
    values: dict[int, float] = {}
    with open(path, newline="") as f:
        for row in csv.reader(f):
            try:
                step, value = int(float(row[0])), float(row[1])
            except (IndexError, ValueError):
                continue
            values[step] = value
    steps = sorted(values)
    return steps, [values[s] for s in steps]


# Where torchrl's CSVLogger puts ``train/*loss*`` scalars (imitation's loss, loss_action ...; SB3's actor_loss,
# critic_loss ...), seen from a training run folder (``logs/<exp_name>/scalars/...``), one experiment folder, or a
# ``scalars`` folder. Fixed depths, no recursive search: the default source is the policy file's folder, which may
# hold anything.
LOSS_PATTERNS = ("logs/*/scalars/train/*loss*.csv", "scalars/train/*loss*.csv", "train/*loss*.csv")


def loss_csvs(source: pathlib.Path) -> list[pathlib.Path]:
    """The ``train/*loss*.csv`` scalar files of a training run, experiment or ``scalars`` folder."""
    return sorted({path for pattern in LOSS_PATTERNS for path in source.glob(pattern)})


def plot_loss_curves(source: pathlib.Path, out_png: pathlib.Path) -> pathlib.Path | None:
    """Plot the training loss curves logged under ``source`` (a run folder or a ``scalars`` folder).

    Curves are named by file (``loss``, ``loss_action``, ``loss_vision``; SB3's ``actor_loss``, ``critic_loss``
    ...), prefixed by the experiment folder when several runs log there. Log scale when every value is positive.

    Returns:
        ``out_png``, or None (nothing written) when there are no loss logs.
    """
    files = loss_csvs(pathlib.Path(source))
    curves = {path: read_scalar_csv(path) for path in files}
    curves = {path: curve for path, curve in curves.items() if curve[0]}
    if not curves:
        return None
    several_runs = len({path.parents[1] for path in curves}) > 1
    fig = Figure(figsize=(6, 3.5), layout="constrained")
    ax = fig.add_subplot()
    for path, (steps, values) in curves.items():
        ax.plot(steps, values, label=f"{path.parents[2].name}: {path.stem}" if several_runs else path.stem)
    if all(v > 0 for _, values in curves.values() for v in values):
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.legend()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, out_png)
    return out_png


def plot_learning_curve(curve: list[dict], out_png: pathlib.Path, title: str) -> pathlib.Path:
    """Success rate (with its 95% interval) against env steps, one point per periodic evaluation
    (``{"env_steps", "success_rate", "ci95_low", "ci95_high"}`` each)."""
    fig = Figure(figsize=(6, 3.5), layout="constrained")
    ax = fig.add_subplot()
    steps = [point["env_steps"] for point in curve]
    ax.plot(steps, [100 * point["success_rate"] for point in curve], marker="o")
    ax.fill_between(steps, [100 * point["ci95_low"] for point in curve], [100 * point["ci95_high"] for point in curve],
                    alpha=0.2)
    ax.set_xlabel("env steps")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.set_title(title)
    save_png(fig, out_png)
    return out_png


def save_png(fig: Figure, out_png: pathlib.Path) -> None:
    """Write ``fig`` as a PNG, atomically."""
    with atomic_write(out_png, "wb") as f:
        fig.savefig(f, format="png", dpi=100)
