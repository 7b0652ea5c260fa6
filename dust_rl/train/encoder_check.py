"""Can the policy see the objects? Linear probes of object positions from frozen image features.

A policy conditioned on frozen features can only act on what the features
keep. The cheapest test of that is a linear read-out: every dataset row
stores the privileged object state (``observation.environment_state``:
object positions, joint openings), so a ridge regression from one camera's
feature tokens to those numbers, fitted on some episodes and scored (R^2) on
others, says how well the positions can be read off. Measured on 200
pick_place episodes: the project's 4x4 autoencoder latent reads the two
cubes' xy at R^2 ~0.7 and grasps fail a centimetre or two beside the cube;
see BENCHMARKS.md for the EfficientNet-Lite rows.

Episodes, not rows, are split: rows of one episode share the object layout,
so a row-level split would score memorisation of layouts.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

import torch
from matplotlib.figure import Figure
from torch import Tensor
from tqdm.auto import tqdm

from dust_rl.agents.encoders.image_encoder import ImageEncoder, image_tokens
from dust_rl.data import DemoDataset
from dust_rl.evaluate.report import save_png
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY
from dust_rl.storage.atomic_files import write_json_atomic

RIDGE_ALPHAS = (1e-2, 1e-1, 1.0, 10.0, 100.0, 1000.0)


@dataclass(frozen=True)
class ProbeResult:
    """Held-out R^2 of each target column, with the ridge strength picked on validation episodes."""

    r2: Tensor
    columns: list[int]
    alpha: float
    train_rows: int
    heldout_rows: int


def _ridge(x: Tensor, y: Tensor, alpha: float) -> Tensor:
    """Ridge weights [D + 1, K] (last row: intercept) in float64; the dual form when rows < features."""
    x1 = torch.cat([x, torch.ones(x.shape[0], 1, dtype=x.dtype)], dim=1)
    if x1.shape[0] < x1.shape[1]:
        gram = x1 @ x1.T + alpha * torch.eye(x1.shape[0], dtype=x.dtype)
        return x1.T @ torch.linalg.solve(gram, y)
    reg = alpha * torch.eye(x1.shape[1], dtype=x.dtype)
    reg[-1, -1] = 0.0  # the intercept is not shrunk
    return torch.linalg.solve(x1.T @ x1 + reg, x1.T @ y)


def _predict(w: Tensor, x: Tensor) -> Tensor:
    return x @ w[:-1] + w[-1]


def r2_score(pred: Tensor, target: Tensor, variance: Tensor) -> Tensor:
    """1 - mean squared error / ``variance`` per column (1 = perfect, 0 = no better than the mean).

    The variance is that of all probed rows, not of the held-out ones alone: a few held-out episodes may
    hold a column (nearly) constant, which would make the usual held-out R^2 undefined.
    """
    return 1.0 - (pred - target).square().mean(0) / variance


def linear_probe(features: Tensor, targets: Tensor, groups: Tensor, heldout_fraction: float = 0.2,
                 seed: int = 0, columns: list[int] | None = None) -> ProbeResult:
    """Fit ridge read-outs of ``targets`` from ``features`` on some groups, score R^2 on the others.

    Args:
        features: [N, D] (flattened tokens).
        targets: [N, K].
        groups: [N] int group (episode) of each row; whole groups go to train, validation or held-out.
        heldout_fraction: share of groups held out for the score (the same share again picks alpha).
        seed: shuffles the groups.
        columns: names (indices) of the target columns, for the report; default 0..K-1.

    Raises:
        ValueError: fewer than 3 groups, or shapes that do not line up.
    """
    if features.shape[0] != targets.shape[0] or groups.shape != features.shape[:1]:
        raise ValueError(f"rows differ: features {tuple(features.shape)}, targets {tuple(targets.shape)}, "
                         f"groups {tuple(groups.shape)}")
    ids = groups.unique()
    if len(ids) < 3:
        raise ValueError(f"a probe needs >= 3 episodes to split, got {len(ids)}")
    ids = ids[torch.randperm(len(ids), generator=torch.Generator().manual_seed(seed))]
    n_out = max(1, round(heldout_fraction * len(ids)))
    heldout, val = torch.isin(groups, ids[:n_out]), torch.isin(groups, ids[n_out:2 * n_out])
    train = ~(heldout | val)
    x, y = features.double(), targets.double()
    mean, std = x[train].mean(0), x[train].std(0).clamp_min(1e-6)
    x = (x - mean) / std
    variance = y.var(0).clamp_min(torch.finfo(y.dtype).tiny)

    def fit_score(fit: Tensor, score: Tensor, alpha: float) -> Tensor:
        return r2_score(_predict(_ridge(x[fit], y[fit], alpha), x[score]), y[score], variance)

    alpha = max(RIDGE_ALPHAS, key=lambda a: fit_score(train, val, a).mean().item())
    return ProbeResult(fit_score(train | val, heldout, alpha).float(), columns or list(range(targets.shape[1])),
                       alpha, int((train | val).sum()), int(heldout.sum()))


def probe_dataset(dataset: DemoDataset, encoder: ImageEncoder, grid: tuple[int, int] | None = None,
                  every: int = 8, progress: bool = True) -> dict[str, ProbeResult]:
    """Per camera, the held-out R^2 of every varying ``observation.environment_state`` column read off its tokens.

    Args:
        dataset: rows with images and the privileged environment state.
        encoder: the frozen image encoder.
        grid: token grid the features are pooled to; default: the encoder's own (finest) grid.
        every: probe every n-th row (rows next to each other are near duplicates).
        progress: show a progress bar.

    Note: the wrist camera moves with the hand, so world positions read poorly from it by design;
    its tokens matter for the last centimetres of a grasp, which this probe does not score.
    """
    rows = torch.arange(0, len(dataset), every)
    episodes = torch.repeat_interleave(torch.arange(dataset.num_episodes), dataset.lengths)[rows]
    data = dataset.data[rows]
    targets = data.get(ENV_STATE_KEY).float()
    varying = (targets.std(0) > 0).nonzero().flatten()  # constant columns (padding of smaller tasks) say nothing
    grid = grid or encoder.native_grid()
    results = {}
    for camera in tqdm(dataset.cameras, desc="probing cameras", disable=not progress):
        images = data.get((*IMAGE_KEY, camera))
        with torch.no_grad():
            tokens = torch.cat([image_tokens(encoder, chunk, grid) for chunk in images.split(64)])
        results[camera] = linear_probe(tokens.flatten(1), targets[:, varying], episodes, columns=varying.tolist())
    return results


def write_encoder_check(results: dict[str, ProbeResult], out: pathlib.Path, title: str) -> dict[str, pathlib.Path]:
    """``probe.json`` and ``probe.png`` (held-out R^2 per environment-state column, a bar per camera)."""
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "probe.json", "plot": out / "probe.png"}
    write_json_atomic(paths["json"], {"title": title, "cameras": {
        cam: {"r2": r.r2.tolist(), "columns": r.columns, "alpha": r.alpha, "train_rows": r.train_rows,
              "heldout_rows": r.heldout_rows}
        for cam, r in results.items()}}, indent=2)
    names = [f"env[{c}]" for c in next(iter(results.values())).columns]
    columns = len(names)
    fig = Figure(figsize=(max(4.0, 0.5 * columns + 2), 3.5), layout="constrained")
    ax = fig.add_subplot()
    width = 0.8 / len(results)
    for i, (camera, result) in enumerate(results.items()):
        ax.bar([c + i * width for c in range(columns)], result.r2.clamp_min(-0.1).tolist(), width, label=camera)
    ax.set_xticks([c + 0.4 - width / 2 for c in range(columns)], names, rotation=45)
    ax.set_ylim(-0.1, 1)
    ax.set_ylabel("held-out R^2 (linear probe)")
    ax.set_title(title, fontsize=9)
    ax.legend()
    save_png(fig, paths["plot"])
    return paths
