"""The built-in outputs with settings of their own, registered by importing their modules."""
from flightsim.outputs import device_las, photon_las  # noqa: F401
