"""The kernel side of an instrument's parts, and how they compose.

An instrument is an emitter (the beams of one pulse, in the emitter frame) followed by a
deflector (what turns those beams, per pulse, into rays leaving the sensor). Each kind of part
is one module of ``@wp.func``s plus a parameter ``@wp.struct``; the kernels of
:mod:`kernels.trace` are built for one :class:`Instrument` (cached), so a run compiles and pays
for only the parts it uses. A new kind is one module defining an :class:`Emitter` or
:class:`Deflector` and one registration on the host (``flightsim.instrument.parts``).
"""
from dataclasses import dataclass
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@dataclass(frozen=True)
class Emitter:
    """The beams of a pulse.

    params: the ``@wp.struct`` of the emitter's parameters;
    direction(b: int, params) -> wp.vec3d: unit direction of beam b [emitter frame, +z the beam axis],
    tabulated once per run.
    """

    name: str
    params: type
    direction: wp.Function


@dataclass(frozen=True)
class Deflector:
    """A beam deflector split by what each stage depends on.

    params: the ``@wp.struct`` of its parameters; the truth and the processing's belief are two
    instances of it (every geometric parameter and every scan-angle error exists twice);
    beam_stage(s1: vec3d, params) -> vec3d: depends on the beam only (tabulated once per run, float64);
    pulse_stage(table, row, p, params): depends on the pulse only: writes ``pulse_rows`` float64 rows
    from ``row`` of column p of the pulse table, reading the pose rows (scan angle, pulse index, seed);
    finish(beam_state, table, row, p, params) -> (direction, exit point [m], ok): the rest, per beam,
    in the precision of ``beam_state`` (float32 or float64), reading the rows its pulse stage wrote;
    rigid_nominal: whether the rigid-array model (the fan leaves with its incident shape around the
    deflected on-axis ray) is defined for this deflector.
    """

    name: str
    params: type
    pulse_rows: int
    beam_stage: wp.Function
    pulse_stage: wp.Function
    finish: wp.Function
    rigid_nominal: bool = False


@dataclass(frozen=True)
class Instrument:
    """An emitter and a deflector: the key every per-instrument kernel and struct is built for."""

    emitter: Emitter
    deflector: Deflector


@wp.func
def get3_as(table: wp.array2d(dtype=wp.float64), row: int, p: int, like: Any):
    """The 3-vector in rows row … row + 2 of column p, in the precision of ``like``."""
    return type(like)(type(like[0])(table[row, p]), type(like[0])(table[row + 1, p]),
                      type(like[0])(table[row + 2, p]))


@wp.func
def standard_normal64(state: wp.uint32):
    """(float64 standard normal deviate, advanced state): Box–Muller, the uniforms drawn in separate
    statements. A Warp function gets the state by value, so the caller must carry on with the
    returned state or its next draw repeats this one."""
    u1 = wp.float64(wp.randf(state))
    u2 = wp.float64(wp.randf(state))
    value = wp.sqrt(wp.float64(-2.0) * wp.log(wp.max(u1, wp.float64(1.0e-12)))) * wp.cos(
        wp.float64(6.283185307179586) * u2)
    return value, state
