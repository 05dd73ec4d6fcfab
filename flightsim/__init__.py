"""flightsim: GPU-first lidar simulator. An instrument is a composition of parts (emitter, deflector,
detector, platform, error model) run by Warp kernels over triangle-mesh scenes.

Public API: :func:`load_config`, :func:`simulate` (a :class:`Result` with every product), :func:`sweep`,
:func:`budget`, and :func:`register_part` for parts defined outside the package (see flightsim.api).
"""

from flightsim.core.version import __version__

__all__ = ["Result", "Returns", "__version__", "budget", "load_config", "register_part", "simulate", "sweep"]


def __getattr__(name: str):
    """The public API, imported on first use: a process that needs only one part (a LAZ worker importing
    the tile writer) does not pay for the rest (config, trajectories, SciPy)."""
    if name in __all__:
        from flightsim import api

        return getattr(api, name)
    raise AttributeError(f"module 'flightsim' has no attribute {name!r}")
