"""flightsim: GPU-first simulator of airborne array-beam lidar through a rotating Risley wedge prism."""

__version__ = "0.1.0"
