"""Provenance for the files a run writes (config.json, reports, dataset metadata): the command's dataclass config
as JSON values (and back, for a run that resumes with its own settings or a policy file that loads, less the settings
a later version retired) and the versions of the packages that shaped the result."""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import pathlib
import platform
import typing
from collections.abc import Mapping

_VERSIONED_PACKAGES = ("dust-rl", "mujoco", "torch", "torchrl", "tensordict", "gymnasium")
# Config groups whose command-line name is not their field's (and so not the key files store them under): the policy
# a command builds is `--model.*`, as `--policy PATH` is always a policy file.
FLAG_GROUPS = {"policy": "model"}


def flag_path(name: str) -> str:
    """The dotted setting ``name`` (``train.policy.d_model``) as the command line spells it
    (``train.model.d-model``)."""
    *groups, setting = name.split(".")
    return ".".join([*(FLAG_GROUPS.get(group, group) for group in groups), setting.replace("_", "-")])


def config_json(config: object) -> dict:
    """``config`` (a dataclass) as plain JSON values: paths become strings, tuples lists."""
    return json.loads(json.dumps(dataclasses.asdict(config), default=str))


def config_from_json(cls: type, values: dict, **changes) -> object:
    """A ``cls`` (a dataclass) from the JSON ``values`` of its fields as :func:`config_json` wrote them (lists as
    tuples, strings as paths where the field is one, a settings group from its own values; fields absent keep their
    defaults), with ``changes``."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if not f.init or f.name not in values or f.name in changes:
            continue
        value = values[f.name]
        group = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if dataclasses.is_dataclass(group) and isinstance(value, dict):
            value = config_from_json(type(group), value)
        elif isinstance(value, list):
            value = tuple(value)
        elif isinstance(value, str) and pathlib.Path in (hints[f.name], *typing.get_args(hints[f.name])):
            value = pathlib.Path(value)
        kwargs[f.name] = value
    return cls(**kwargs, **changes)


class Retired(typing.NamedTuple):
    """A setting earlier versions had: the one value this version still honours (what every run now has), and the
    commit whose code runs its other values (where the runs that used them reproduce)."""

    value: object
    commit: str


def without_retired(stored: Mapping, retired: Mapping[str, Retired]) -> dict:
    """``stored`` (a config as JSON values, nested configs as dicts) without the ``retired`` settings it holds
    (dotted names reach into nested configs: ``policy.readout_coords``).

    Raises:
        ValueError: a retired setting stored at another value than its retired one (the message names it and the
            commit that still runs it).
    """
    kept = dict(stored)
    for name, setting in retired.items():
        head, _, rest = name.partition(".")
        if rest and isinstance(kept.get(head), Mapping):
            try:
                kept[head] = without_retired(kept[head], {rest: setting})
            except ValueError as err:
                raise ValueError(f"{head}.{err}") from None
        elif not rest and head in kept and kept.pop(head) != setting.value:
            raise ValueError(f"{name} = {stored[head]!r}: a setting this version removed (only {setting.value!r} is "
                             f"still built; the code that ran other values is at commit {setting.commit})")
    return kept


def retired_values(retired: Mapping[str, Retired]) -> dict[str, object]:
    """The value each ``retired`` setting is still honoured at, by name."""
    return {name: setting.value for name, setting in retired.items()}


def package_versions() -> dict[str, str | None]:
    """Python's version and those of the packages that shape datasets and runs (None: not installed).

    Recorded in dataset metadata and in each training run's ``config.json``.
    """
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in _VERSIONED_PACKAGES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions
