"""Demonstration datasets: collection with torchrl collectors, memmap storage, training windows, LeRobot interop.

LeRobot export/import live in ``dust_rl.data.lerobot_export`` / ``lerobot_import`` (they load pyarrow and PyAV).
"""

from dust_rl.errors import DatasetError

from .collect import collect_demos, demo_collector
from .dataset import DemoDataset
from .windows import DemoWindows

__all__ = ["DatasetError", "DemoDataset", "DemoWindows", "collect_demos", "demo_collector"]
