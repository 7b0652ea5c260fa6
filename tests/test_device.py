"""``--runtime.device``: names resolve to what torch can use here, anything else is refused with the reason."""

from __future__ import annotations

import pytest
import torch

from dust_rl.agents.model.flow_matching import cpu_drawn
from dust_rl.errors import ConfigError
from dust_rl.runtime.device import resolve_device


def test_auto_picks_the_accelerator_torch_sees():
    expected = "cuda" if torch.cuda.is_available() else "mps" if torch.backends.mps.is_available() else "cpu"
    assert resolve_device("auto").type == expected
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.parametrize("name", ["tpu", "gpu", "cuda:x", ""])
def test_unknown_device_names_are_refused(name):
    with pytest.raises(ConfigError, match="unknown device"):
        resolve_device(name)


def test_a_cuda_device_past_the_last_is_refused():
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ConfigError, match="CUDA device"):
        resolve_device(f"cuda:{count}")


def test_noise_is_drawn_on_the_cpu_whatever_the_target_device():
    """Moved to the target device, the numbers are the CPU generator's (torch refuses a CPU generator for a
    CUDA draw, and a CUDA generator would give other numbers)."""
    drawn = cpu_drawn(torch.randn, 4, 3, generator=torch.Generator().manual_seed(7), device="meta")
    assert drawn.device.type == "meta" and drawn.shape == (4, 3)
    again = cpu_drawn(torch.randn, 4, 3, generator=torch.Generator().manual_seed(7), device="cpu")
    assert torch.equal(again, torch.randn(4, 3, generator=torch.Generator().manual_seed(7)))
