"""The built-in products, registered by importing their modules."""
from flightsim.engine.products import las, photons, waveforms  # noqa: F401
