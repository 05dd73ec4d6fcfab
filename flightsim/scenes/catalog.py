"""The built-in scene kinds, registered by importing their modules."""
from flightsim.scenes import calibration, dem, footprint, lunar, mesh, plane, pointcloud, smallbody  # noqa: F401
