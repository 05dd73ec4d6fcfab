"""flightsim: GPU-first lidar simulator. An instrument is a composition of parts (emitter, deflector,
detector, platform, error model) run by Warp kernels over triangle-mesh scenes.

Public API: :func:`load_config`, :func:`simulate`, :func:`sweep`, :func:`budget` (see flightsim.api).
"""

__version__ = "0.1.0"

from flightsim.api import SimulationResult, budget, load_config, simulate, sweep  # noqa: E402

__all__ = ["SimulationResult", "__version__", "budget", "load_config", "simulate", "sweep"]
