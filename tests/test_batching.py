"""Whether a batch of runs may go to worker processes: nothing may carry a gradient."""
import dataclasses

import torch

from flowins.batching import carries_gradient
from flowins.navigation import NavigationConfig


def test_carries_gradient_finds_a_tensor_deep_in_a_config():
    config = NavigationConfig()
    assert not carries_gradient(config, [1.0, "a"], {"k": torch.zeros(2)})
    scale = torch.tensor(2.0, requires_grad=True)
    deep = dataclasses.replace(config, flow_update=dataclasses.replace(config.flow_update, sigma_scale=scale))
    assert carries_gradient(deep)
    assert carries_gradient({"a": [(None, scale)]})
    with torch.no_grad():
        assert not carries_gradient(deep)
