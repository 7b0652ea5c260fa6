"""A command's dataclass config as JSON values, for the files a run writes (config.json, reports)."""

from __future__ import annotations

import dataclasses
import json


def config_json(config: object) -> dict:
    """``config`` (a dataclass) as plain JSON values: paths become strings, tuples lists."""
    return json.loads(json.dumps(dataclasses.asdict(config), default=str))
