"""``--backend ray`` for eval and collect: the same episodes as the local backend, and its refusals.

The refusals run without Ray; the Ray runs need ``pip install "dust-rl[ray]"`` (scripts/nightly.sh installs it)
and start a local Ray cluster (~15-20 s each on 2 cores), so they are slow tests.
"""

from __future__ import annotations

import dataclasses
import importlib.util

import pytest
import torch
from test_cli_errors import collect_args, error_of
from test_evaluate import tiny_policy_file

from dust_rl.data import DemoDataset, collect_demos
from dust_rl.errors import ConfigError
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate
from dust_rl.runtime.settings import RuntimeSettings
from dust_rl.runtime.workers import Workers

pytestmark = pytest.mark.usefixtures("one_thread")


def test_bad_backend_settings_are_refused():
    with pytest.raises(ConfigError, match="unknown backend 'dask'"):
        Workers(2, "dask")
    with pytest.raises(ConfigError, match="ray_address needs backend='ray'"):
        Workers(2, "local", ray_address="auto")
    with pytest.raises(ConfigError, match="count must be >= 1, got 0"):
        Workers(0)
    with pytest.raises(ConfigError, match="threads must be >= 1, got 0"):
        Workers(2, threads=0)
    assert "ray_address needs backend='ray'" in error_of([*collect_args("unused"), "--ray-address", "auto"])


def test_missing_ray_says_how_to_install(monkeypatch):
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *args: None if name == "ray"
                        else real_find_spec(name, *args))
    with pytest.raises(ConfigError, match=r'pip install "dust-rl\[ray\]"'):
        Workers(2, "ray")


@pytest.mark.slow
def test_ray_evaluation_runs_the_local_episodes(tmp_path, minilm):
    pytest.importorskip("ray")
    config = EvalConfig(policy=tiny_policy_file(tmp_path / "policy.pt", minilm), out=tmp_path / "local", episodes=4,
                        workers=1, max_steps=10, videos=1, runtime=RuntimeSettings(progress=False))
    local = evaluate(config)
    on_ray = evaluate(dataclasses.replace(config, out=tmp_path / "ray", workers=2, backend="ray"))
    assert on_ray["tasks"][0]["per_episode"] == local["tasks"][0]["per_episode"]
    assert on_ray["tasks"][0]["videos"][0]["digest"] == local["tasks"][0]["videos"][0]["digest"]
    assert on_ray["config"]["backend"] == "ray"


@pytest.mark.slow
def test_ray_collection_writes_the_local_dataset(tmp_path, demo_dir):
    pytest.importorskip("ray")
    collect_demos(tmp_path / "ray", tasks=["press_button"], episodes=3, env_kwargs={"image_size": 32},
                  workers=Workers(2, "ray"), progress=False)
    on_ray, reference = DemoDataset(tmp_path / "ray"), DemoDataset(demo_dir)  # reference: local, in-process
    assert [e["seed"] for e in on_ray.meta["episodes"]] == [e["seed"] for e in reference.meta["episodes"][:3]]
    rows = on_ray.data.shape[0]
    for key in ("action", ("observation", "state"), ("observation", "image", "front")):
        assert torch.equal(on_ray.data[key], reference.data[key][:rows]), key
