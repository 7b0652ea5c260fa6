"""bf16 autocast and torch.compile of the trunk, in training and sampling (run here on the CPU)."""

from __future__ import annotations

import pytest
import torch
from conftest import rounding_tolerance
from test_train import TINY_POLICY, run_inputs, tiny_config  # noqa: F401 (run_inputs is a fixture)

from dust_rl.agents import DustPolicy, load_policy
from dust_rl.data import DemoDataset, DemoWindows
from dust_rl.train.imitation import train

pytestmark = pytest.mark.usefixtures("one_thread")

DEPTH = TINY_POLICY["n_mmdit"] + TINY_POLICY["n_dit"] + 2  # blocks, plus the input and output layers


def second_loss(out) -> float:
    """The loss logged at step 2: at step 1 the zero-initialised output layers give the same loss at any
    precision."""
    return float((out / "logs" / "train" / "scalars" / "train" / "loss.csv").read_text().split()[1].split(",")[1])


def planned(policy: DustPolicy, dataset) -> torch.Tensor:
    observations = next(DemoWindows(DemoDataset(dataset), horizon=4, batch_size=4).iterate(4))
    return policy.eval().plan(observations, generator=torch.Generator().manual_seed(0))["action_chunk"]


def test_bf16_trains_and_samples_close_to_fp32(run_inputs, tmp_path):  # noqa: F811
    fp32 = train(tiny_config(run_inputs, tmp_path / "fp32", steps=2, log_every=1))
    bf16 = train(tiny_config(run_inputs, tmp_path / "bf16", steps=2, log_every=1, precision="bf16"))
    assert all(v.dtype == torch.float32 for v in load_policy(bf16.policy).state_dict().values()
               if v.is_floating_point())  # autocast leaves the stored weights float32
    expected, actual = second_loss(tmp_path / "fp32"), second_loss(tmp_path / "bf16")
    assert actual != expected and torch.isfinite(torch.tensor(actual))  # the products did run in bf16

    policy = load_policy(fp32.policy)
    reference = planned(policy, run_inputs[0])
    policy.set_runtime(precision="bf16")
    chunk = planned(policy, run_inputs[0])
    assert chunk.dtype == torch.float32 and not torch.equal(chunk, reference)
    scale = reference.abs().max().item()
    torch.testing.assert_close(chunk, reference, rtol=0,
                               atol=rounding_tolerance(torch.bfloat16, TINY_POLICY["d_model"], DEPTH, scale))


@pytest.mark.slow  # inductor compiles C++ kernels: tens of seconds on 2 cores, and it needs a compiler
def test_compiled_trunk_trains_and_samples_like_eager(run_inputs, tmp_path):  # noqa: F811
    eager = train(tiny_config(run_inputs, tmp_path / "eager", steps=2, log_every=1))
    train(tiny_config(run_inputs, tmp_path / "compiled", steps=2, log_every=1, compile=True))
    expected = second_loss(tmp_path / "eager")
    assert abs(second_loss(tmp_path / "compiled") - expected) <= rounding_tolerance(
        torch.float32, TINY_POLICY["d_model"], DEPTH, expected)
    policy = load_policy(eager.policy)
    reference = planned(policy, run_inputs[0])
    policy.set_runtime(compile=True)
    chunk = planned(policy, run_inputs[0])
    torch.testing.assert_close(chunk, reference, rtol=0, atol=rounding_tolerance(
        torch.float32, TINY_POLICY["d_model"], DEPTH, reference.abs().max().item()))
