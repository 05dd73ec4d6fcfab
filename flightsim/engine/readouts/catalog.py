"""The built-in readouts, registered by importing their modules."""
from flightsim.engine.readouts import deviations, photons, points, statistics, waveforms  # noqa: F401
