"""The simulated "snowy city block" walk (the paper's scenario, whose data are not public).

``scenario`` (configuration, generation, caching), ``world`` (the city), ``render``
(torch ray casting and exact optical flow), ``gnss`` (urban-canyon GNSS errors).
Command line: ``python -m flowins.data.simulate OUT --seed 0 --duration 300``.
"""
from flowins.data.simulate.scenario import (
    CameraConfig,
    SimulationConfig,
    default_cache_dir,
    simulate,
)

__all__ = ["CameraConfig", "SimulationConfig", "default_cache_dir", "simulate"]
