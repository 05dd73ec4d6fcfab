"""The fixed deflector: beams leave the sensor origin as emitted (a staring instrument)."""
from typing import Any

import warp as wp

from kernels.parts import Deflector

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.struct
class Fixed:
    """No parameters (a struct needs a field)."""

    unused: wp.int32


@wp.func
def fixed_beam_stage(s1: Any, f: Fixed):
    return s1


@wp.func
def fixed_pulse_stage(table: wp.array2d(dtype=wp.float64), row: int, p: int, f: Fixed):
    pass


@wp.func
def fixed_finish(s: Any, table: wp.array2d(dtype=wp.float64), row: int, p: int, f: Fixed):
    """(s, origin, True)."""
    return s, type(s)(), True


FIXED = Deflector("fixed", Fixed, 0, fixed_beam_stage, fixed_pulse_stage, fixed_finish)
