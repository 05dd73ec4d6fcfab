"""The built-in scene kinds, registered by importing their modules."""
from flightsim.scenes import (calibration, dem, footprint, forest_scene, lunar, mesh, plane, pointcloud,  # noqa: F401
                              smallbody)
