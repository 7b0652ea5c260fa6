"""Packaging: version ranges and their exact pins, ``__version__``, a light ``import dust_rl``, and the dm_env face.

Why these matter: exact pins in pyproject.toml made dust-rl impossible to install beside other libraries (LeRobot,
stable-baselines3), so pyproject.toml asks for ranges and constraints.txt keeps the tested versions; the two must
agree or ``pip install -c constraints.txt`` fails to resolve. ``import dust_rl`` registers the gymnasium ids and
runs in every worker process, so it must not pay for torch.
"""

from __future__ import annotations

import importlib.metadata
import json
import pathlib
import subprocess
import sys
import unittest

import dm_env
import gymnasium as gym
import numpy as np
import pytest
from dm_env import specs, test_utils
from packaging.requirements import Requirement

import dust_rl
from dust_rl.envs import DustEnv
from dust_rl.envs.dm_env_adapter import DmEnvAdapter, make_dm_env

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _project() -> dict:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _requirements() -> list[Requirement]:
    project = _project()
    lines = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        lines += extra
    return [Requirement(line) for line in lines]


def _constraints() -> dict[str, Requirement]:
    lines = [line.strip() for line in (ROOT / "constraints.txt").read_text().splitlines()]
    pins = [Requirement(line) for line in lines if line and not line.startswith("#")]
    return {_normalized(pin.name): pin for pin in pins}


def _normalized(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


# -- version ranges and constraints -------------------------------------------------------------------------------


def test_pyproject_asks_for_ranges_not_exact_versions():
    exact = [str(req) for req in _requirements() if any(s.operator in ("==", "===") for s in req.specifier)]
    # torch is the one exact pin: a range lets pip pull a newer, multi-GB CUDA build on a fresh machine.
    assert exact == ["torch==2.13.0"], f"exact pins belong in constraints.txt, not pyproject.toml: {exact}"


def test_every_requirement_has_an_exact_pin_inside_its_range():
    pins = _constraints()
    for req in _requirements():
        pin = pins.get(_normalized(req.name))
        assert pin is not None, f"{req.name} has no pin in constraints.txt"
        (spec,) = pin.specifier
        assert spec.operator == "==", f"constraints.txt pins exact versions; {pin} is not one"
        assert req.specifier.contains(spec.version), f"constraints.txt's {pin} is outside pyproject's {req}"


def test_constraints_pin_only_what_pyproject_asks_for():
    asked = {_normalized(req.name) for req in _requirements()}
    stray = sorted(set(_constraints()) - asked)
    assert not stray, f"constraints.txt pins packages pyproject.toml does not ask for: {stray}"


def test_every_package_folder_and_its_data_is_in_the_wheel():
    """pyproject lists the packages one by one: a subpackage missing from the list, or a package-data pattern that
    matches nothing, would be left out of a wheel while the editable install works."""
    tomllib = pytest.importorskip("tomllib")
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = setuptools["package-dir"]

    def folder(package: str) -> pathlib.Path:
        root = max((p for p in folders if package == p or package.startswith(p + ".")), key=len)
        return ROOT / folders[root] / pathlib.Path(*package.removeprefix(root).split(".")[1:])

    found = {".".join([package, *init.parent.relative_to(ROOT / path).parts])
             for package, path in folders.items() for init in (ROOT / path).rglob("__init__.py")}
    assert found == set(setuptools["packages"])
    for package, patterns in setuptools["package-data"].items():
        assert all(list(folder(package).glob(pattern)) for pattern in patterns), (package, patterns)


def test_setup_installs_with_the_constraints_and_reinstalls_when_they_change():
    setup = (ROOT / "scripts" / "setup.sh").read_text()
    stamp = next(line for line in setup.splitlines() if line.startswith("want="))
    assert "pyproject.toml" in stamp and "constraints.txt" in stamp
    installs = [line for line in setup.splitlines() if "pip install" in line]
    assert installs and all("-c constraints.txt" in line for line in installs)


# -- __version__ and a light import -------------------------------------------------------------------------------


def test_version_is_the_installed_distributions():
    assert dust_rl.__version__ == importlib.metadata.version("dust-rl") == _project()["version"]


def _run(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True,
                          timeout=120).stdout


def test_version_flag_prints_the_installed_version():
    assert _run("from dust_rl.cli import main; main(['--version'])").strip() == \
        f"dust-rl {importlib.metadata.version('dust-rl')}"


def test_version_falls_back_when_the_package_is_not_installed():
    code = """
from importlib import metadata
def missing(name):
    raise metadata.PackageNotFoundError(name)
metadata.version = missing
import dust_rl
print(dust_rl.__version__)
"""
    assert _run(code).strip() == "0+unknown"


def test_import_registers_the_envs_without_torch():
    code = """
import json, sys
import dust_rl, gymnasium
print(json.dumps({"modules": sorted(sys.modules), "ids": sorted(gymnasium.registry)}))
"""
    loaded = json.loads(_run(code))
    heavy = {"torch", "tensordict", "torchrl", "dust_rl.agents", "dust_rl.envs.env"} & set(loaded["modules"])
    assert not heavy, f"import dust_rl loaded {sorted(heavy)}"
    assert {"DustFranka-v0", "DustHumanoid-v0"} <= set(loaded["ids"])


def test_env_names_still_load_from_dust_rl_envs():
    import dust_rl.envs

    assert dust_rl.envs.DustEnv is DustEnv and "push" in dust_rl.envs.list_tasks()
    with pytest.raises(AttributeError, match="no attribute 'Nothing'"):
        dust_rl.envs.Nothing  # noqa: B018


# -- dm_env ------------------------------------------------------------------------------------------------------


class DmEnvContract(test_utils.EnvironmentTestMixin, unittest.TestCase):
    """dm_env's own checks of the interface: FIRST after reset and after LAST, specs match every TimeStep."""

    def make_object_under_test(self) -> DmEnvAdapter:
        return DmEnvAdapter(DustEnv(task="press_button", image_size=32, max_episode_steps=4), seed=0)

    def make_action_sequence(self):
        for _ in range(10):  # past two time limits: LAST, then FIRST
            yield self.make_action()


def test_specs_mirror_the_gymnasium_spaces():
    with make_dm_env(task="push", image_size=32) as env:
        space = env.env.observation_space
        obs_spec = env.observation_spec()
        assert set(obs_spec) == set(space)
        front = obs_spec["observation.image.front"]
        assert isinstance(front, specs.BoundedArray) and front.shape == (32, 32, 3) and front.dtype == np.uint8
        state = obs_spec["observation.state"]
        assert type(state) is specs.Array and state.shape == space["observation.state"].shape
        assert isinstance(obs_spec["language_instruction"], specs.StringArray)
        action = env.action_spec()
        assert action.shape == (7,) and action.dtype == np.float32
        np.testing.assert_array_equal(action.minimum, -1.0)
        np.testing.assert_array_equal(action.maximum, 1.0)


def test_time_limit_is_a_truncation_with_discount_one():
    with DmEnvAdapter(DustEnv(task="push", obs_mode="state", max_episode_steps=3), seed=0) as env:
        steps = [env.reset()] + [env.step(np.zeros(7, np.float32)) for _ in range(3)]
    assert [s.step_type for s in steps] == [dm_env.StepType.FIRST] + [dm_env.StepType.MID] * 2 + [dm_env.StepType.LAST]
    assert [s.discount for s in steps[1:]] == [1.0, 1.0, 1.0]
    assert env.info["truncation_reason"] == "time_limit" and not env.info["is_success"]


def test_success_terminates_with_discount_zero():
    with DmEnvAdapter(DustEnv(task="press_button", obs_mode="state"), seed=0) as env:
        expert = env.env.make_expert()
        step = env.reset()
        expert.reset()
        while not step.last():
            assert step.first() or step.discount == 1.0
            step = env.step(expert.act())
    assert step.discount == 0.0 and step.reward == 1.0 and env.info["is_success"]


def test_seed_reproduces_the_episodes():
    def first_states(seed: int) -> list[np.ndarray]:
        with DmEnvAdapter(DustEnv(task="push", obs_mode="state"), seed=seed) as env:
            return [env.reset().observation["environment_state"] for _ in range(2)]

    a, b, c = first_states(5), first_states(5), first_states(6)
    np.testing.assert_array_equal(np.stack(a), np.stack(b))
    assert not np.array_equal(a[0], a[1]) and not np.array_equal(a[0], c[0])


def test_unsupported_spaces_say_what_is_expected():
    with pytest.raises(TypeError, match="Dict observation space"):
        DmEnvAdapter(gym.make("CartPole-v1"))
