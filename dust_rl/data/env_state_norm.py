"""Per-task normalisation of the privileged object state that the read-out learns to estimate.

Why per task: each task lays its object state out its own way (pick_place: two cubes' and the plate's xyz;
press_button: three buttons' xyz and travel; the drawers: handle, cabinet, yaw, opening), zero-padded to the widest.
One mean and std per column over a multi-task dataset mixes unrelated quantities. On the 8 Franka tasks
(``runs/data/all_100``) column 5 is a second object's height for most tasks (std 2.9 cm over the mixture) but the
middle button's y for press_button (+-20 cm), so one task's rows dominated the read-out's loss (fitted alone with
the pooled statistics, a normalised squared error of 2.01 in that column against at most 0.39 in the others); the
first multi-task run's read-out error on held-out aux frames stayed at 0.22-0.35 (normalised) against 0.004 on
pick_place alone. Here each task is normalised by its own rows over its own columns and its padding stays 0. Fitted
alone (``experiments/token_readout_probe.py --heads 4 --frames 8000 --steps 4000``), the read-out's held-out xy error on
the first object fell from 7.2 to 4.4 cm (docs/franka_results.md, "The Franka suite, one policy"). A one-task
dataset gets exactly the statistics in its ``meta.json``: single-task training is unchanged. The policy itself
never needs the statistics (the read-out's estimate stays in normalised units inside it); diagnostics that turn it
back into metres do, and a policy's ``info`` says which normalisation it was trained with (multi-task policies
trained before this module used the pooled statistics).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from dust_rl.agents import DustPolicy
from dust_rl.agents.normalizer import MIN_STD
from dust_rl.data import DatasetError, DemoDataset
from dust_rl.keys import ENV_STATE_KEY, flat_name

INFO_KEY, PER_TASK = "env_state_norm", "per_task"  # in a trained policy's ``info``


class EnvStateNorm:
    """Mean and std of the object state, one row per task.

    Args:
        tasks: the task names, in the order of ``mean``'s rows (a dataset's ``tasks``).
        mean, std: [T, S] in the state's units; std already floored at :data:`MIN_STD`.
    """

    def __init__(self, tasks: Sequence[str], mean: Tensor, std: Tensor) -> None:
        if mean.shape != std.shape or mean.shape[0] != len(tasks):
            raise ValueError(f"mean {tuple(mean.shape)} and std {tuple(std.shape)} need one row per task "
                             f"({len(tasks)})")
        self.tasks, self.mean, self.std = list(tasks), mean, std

    @classmethod
    def of_dataset(cls, dataset: DemoDataset, per_task: bool = True) -> EnvStateNorm:
        """The statistics of ``dataset``'s rows, task by task (``per_task=False``: the whole dataset's for every
        task, as before this module).

        Raises:
            DatasetError: the dataset stores no environment state (e.g. imported from LeRobot).
        """
        stats = dataset.meta["stats"].get(flat_name(ENV_STATE_KEY))
        if not (stats and stats["mean"]):
            raise DatasetError(f"{dataset.root}: no observation.environment_state to learn from (an imported dataset "
                               "has none); train without the auxiliary state loss")
        if len(dataset.tasks) == 1 or not per_task:
            pooled = torch.tensor([stats["mean"], stats["std"]])
            mean, std = pooled.unsqueeze(1).expand(2, len(dataset.tasks), -1)
            return cls(dataset.tasks, mean, std.clamp_min(MIN_STD))
        states, row_task = dataset.data.get(ENV_STATE_KEY).to(torch.float64), dataset.row_task_index
        width = states.shape[1]
        mean, std = torch.zeros(len(dataset.tasks), width), torch.ones(len(dataset.tasks), width)
        for index, task in enumerate(dataset.tasks):
            values = states[row_task == index, :dataset.meta["environment_state_dims"][task]]
            columns = values.shape[1]
            mean[index, :columns] = values.mean(0).float()
            std[index, :columns] = values.std(0, correction=0).float().clamp_min(MIN_STD)
        return cls(dataset.tasks, mean, std)

    @classmethod
    def of_policy(cls, policy: DustPolicy) -> EnvStateNorm:
        """The normalisation ``policy``'s read-out was trained with (its training dataset's statistics)."""
        return cls.of_dataset(DemoDataset(policy.info["dataset"]), per_task=policy.info.get(INFO_KEY) == PER_TASK)

    def task_indices(self, tasks: Sequence[str]) -> Tensor:
        """The index of each of ``tasks`` in :attr:`tasks` (e.g. another dataset's tasks).

        Raises:
            ValueError: a task these statistics were not computed on.
        """
        unknown = [task for task in tasks if task not in self.tasks]
        if unknown:
            raise ValueError(f"no object-state statistics for {unknown}: they were computed on {self.tasks}")
        return torch.tensor([self.tasks.index(task) for task in tasks], dtype=torch.int64)

    def normalize(self, state: Tensor, task: Tensor) -> Tensor:
        """``state`` [B, S] in normalised units, row b by task ``task[b]`` (an index into ``tasks``)."""
        return (state - self.mean[task]) / self.std[task]

    def denormalize(self, normalised: Tensor, task: Tensor) -> Tensor:
        """The inverse of :meth:`normalize`: back in the state's units."""
        return normalised * self.std[task] + self.mean[task]
