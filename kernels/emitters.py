"""Emitters: the beams of one pulse, as unit directions in the emitter frame (+z the beam axis)."""
import warp as wp

from kernels.optics import doe_direction
from kernels.parts import Emitter

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.struct
class BeamArray:
    """The DOE fan: n×n sub-beams spaced by ``spacing`` [rad]."""

    n: wp.int32
    spacing: wp.float32


@wp.func
def fan_direction(b: int, beams: BeamArray):
    """Sub-beam b = i·n + j of the DOE fan (kernels.optics.doe_direction), float64."""
    return doe_direction(b // beams.n, b % beams.n, beams.n, wp.float64(beams.spacing))


@wp.struct
class Channels:
    """A linear array of channels fanned along the emitter's y axis."""

    angles: wp.array(dtype=wp.float64)  # angle of each channel from the beam axis, towards +y [rad]


@wp.func
def channel_direction(b: int, channels: Channels):
    """Channel b: (0, sin θ_b, cos θ_b)."""
    theta = channels.angles[b]
    return wp.vec3d(wp.float64(0.0), wp.sin(theta), wp.cos(theta))


@wp.struct
class BeamTable:
    """Beams given by their unit directions, tabulated on the host (e.g. ATLAS's three beam pairs)."""

    directions: wp.array(dtype=wp.vec3d)  # unit direction of each beam [emitter frame, +z the axis]


@wp.func
def table_direction(b: int, table: BeamTable):
    """Beam b: its tabulated unit direction, float64."""
    return table.directions[b]


FAN = Emitter("fan", BeamArray, fan_direction)
CHANNELS = Emitter("channels", Channels, channel_direction)
TABLE = Emitter("table", BeamTable, table_direction)
