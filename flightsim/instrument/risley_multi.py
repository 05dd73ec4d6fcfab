"""Two or three rotating wedge prisms in a row (``instrument.deflector = "risley_n"``, ``[risley_n]``): each prism
turns at its own signed rate and phase (co- or counter-rotating, any speed ratio), every face crossed exactly
(kernels/wedges.py), the prism-angle encoders' errors on the truth, and the prisms the georeferencing believes in
(``believed_*``; empty or 0 = the true value).

Per-prism settings are lists of one value (every prism) or one value per prism; ``gap_mm`` has one value or one
per neighbouring pair. The rates are decimals whose ratios must be fractions of whole numbers up to
:data:`~flightsim.instrument.risley_multi_model.MAX_TURNS`: the pattern then repeats every 1/f_p seconds, and the
scan phase 2π·frac(f_p·t) (exact at any GPS time, written to LAS as ``prism_angle``) gives every prism's angle.
The rigid-array (nominal) model is defined for it as for the single wedge: the fan leaving as it entered, around
the on-axis ray traced through the believed prisms.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.constants import ARCSEC
from flightsim.core.errors import InputError
from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.instrument import risley_multi_model as model
from trajectories import PulseTiming

wedges = lazy_module("kernels.wedges")

PER_PRISM = ("rotation_hz", "phase0_deg", "apex_angle_deg", "refractive_index", "thickness_mm", "encoder_arcsec")
BELIEVED = {"believed_refractive_index": "refractive_index", "believed_apex_angle_deg": "apex_angle_deg",
            "believed_thickness_mm": "thickness_mm", "believed_gap_mm": "gap_mm"}
GRID_SAMPLES = 24  # prism angles per turn at which the checks and the reach are traced
REACH_MARGIN_RAD = 1e-3  # added to the traced reach (the grid's angles may miss the widest beam slightly)


def _per_prism(default, doc: str, unit: str, items: tuple[float, float], believed: bool = False):
    more = "; empty (or 0 for a prism) = the true value" if believed else ""
    return setting(default, f"{doc}: one value for every prism or one per prism{more}", unit, items=items, item=float)


@dataclass
class RisleyNSettings(Settings):
    """Two or three wedge prisms on one axis, their rates and phases, encoders' errors and believed geometry."""

    prisms: int = setting(2, "wedge prisms in a row on the axis", "prisms", range=(2, 3))
    prf_hz: float = setting(5000.0, "pulse repetition frequency", "Hz", range=(0.0, 1.0e7), lo_open=True)
    rotation_hz: tuple = _per_prism((20.0, -20.0), "turns per second of each prism, negative the other way",
                                    "Hz", (-1000.0, 1000.0))
    phase0_deg: tuple = _per_prism((90.0,), "prism angle at GPS time 0", "deg", (-360.0, 360.0))
    apex_angle_deg: tuple = _per_prism((10.0,), "wedge apex angle α (0: a flat plate)", "deg", (0.0, 89.0))
    refractive_index: tuple = _per_prism((1.5066,), "refractive index of the glass (BK7 at 1064 nm)", "",
                                         (1.0, 4.0))
    thickness_mm: tuple = _per_prism((10.0,), "centre thickness d", "mm", (0.0, 1000.0))
    gap_mm: tuple = setting((5.0,), "air gap on the axis between a prism's back face and the next one's front "
                            "face: one value or one per neighbouring pair", "mm", items=(0.0, 1000.0), item=float)
    encoder_arcsec: tuple = _per_prism((0.0,), "prism-angle encoder zero error on the truth", "arcsec",
                                       (-3600.0, 3600.0))
    encoder_noise_arcsec: float = setting(0.0, "prism-angle noise per pulse and prism, 1 sigma", "arcsec",
                                          range=(0.0, 3600.0))
    believed_refractive_index: tuple = _per_prism((), "refractive index the processing believes", "", (0.0, 4.0),
                                                  believed=True)
    believed_apex_angle_deg: tuple = _per_prism((), "apex angle the processing believes", "deg", (0.0, 89.0),
                                                believed=True)
    believed_thickness_mm: tuple = _per_prism((), "centre thickness the processing believes", "mm", (0.0, 1000.0),
                                              believed=True)
    believed_gap_mm: tuple = setting((), "gaps the processing believes: one value or one per pair; empty (or 0 for "
                                     "a gap) = the true value", "mm", items=(0.0, 1000.0), item=float)

    def expand(self, name: str, values) -> tuple[float, ...]:
        """A list setting as one value per prism (per gap for the gaps), or InputError naming it."""
        count = self.prisms - 1 if name.endswith("gap_mm") else self.prisms
        values = tuple(float(v) for v in values)
        if len(values) == 1:
            return values * count
        if len(values) != count:
            what = "neighbouring pair" if count == self.prisms - 1 else "prism"
            allowed = (f"1 value (for every {what}) or {count} values (one per {what})" if count > 1
                       else "1 value (one pair)")
            raise InputError(f"risley_n.{name}", ",".join(f"{v:g}" for v in values), allowed)
        return values

    def believed(self, name: str) -> tuple[float, ...]:
        """The believed values of ``name`` (a key of BELIEVED), the true value where none (or 0) is given."""
        truth = self.expand(BELIEVED[name], getattr(self, BELIEVED[name]))
        given = getattr(self, name)
        if not given:
            return truth
        return tuple(b or t for b, t in zip(self.expand(name, given), truth))

    def check(self, context) -> None:
        for name in PER_PRISM + ("gap_mm",):
            self.expand(name, getattr(self, name))
        if pattern(self) is None:
            _bad_rates(self)
        for d in self.expand("thickness_mm", self.thickness_mm):
            if d <= 0.0:
                raise InputError("risley_n.thickness_mm", ",".join(map(str, self.thickness_mm)),
                                 "thicknesses each in (0, 1000] mm")
        for name in BELIEVED:  # each list of 0, 1 or one value per prism (pair)
            self.believed(name)
        if min(self.believed("believed_refractive_index")) <= 1.0:
            raise InputError("risley_n.believed_refractive_index", ",".join(map(str, self.believed_refractive_index)),
                             "0 (the true index) or numbers in (1, 4]")
        for believed in (False, True):
            _check_stack(self, believed)

    def resolved(self) -> "RisleyNSettings":
        """Every list written out per prism (per pair for the gaps), the believed ones filled in."""
        s = super().resolved()
        for name in PER_PRISM + ("gap_mm",):
            setattr(s, name, s.expand(name, getattr(s, name)))
        for name in BELIEVED:
            setattr(s, name, s.believed(name))
        return s


def _bad_rates(s: RisleyNSettings) -> None:
    rates = s.expand("rotation_hz", s.rotation_hz)
    text = ",".join(f"{r:g}" for r in rates)
    if not any(rates):
        raise InputError("risley_n.rotation_hz", text, "at least one prism turning (a non-zero rate)")
    raise InputError("risley_n.rotation_hz", text, f"rates whose ratios are fractions of whole numbers up to "
                                                   f"{model.MAX_TURNS} (e.g. 20,-13.5)")


def pattern(s: RisleyNSettings) -> tuple[float, tuple[int, ...]] | None:
    """(f_p [Hz], turns of each prism per turn of the scan phase), or None (see model.pattern_turns)."""
    return model.pattern_turns(s.expand("rotation_hz", s.rotation_hz))


def stack(s: RisleyNSettings, believed: bool = False) -> model.Stack:
    """The float64 model of the prisms (truth, or as the processing believes them)."""
    if believed:
        values = [s.believed(name) for name in BELIEVED]
    else:
        values = [s.expand(name, getattr(s, name)) for name in BELIEVED.values()]
    n_glass, apex_deg, thickness_mm, gap_mm = values
    return model.Stack(n_glass, tuple(math.radians(a) for a in apex_deg), tuple(d * 1e-3 for d in thickness_mm),
                       tuple(g * 1e-3 for g in gap_mm))


def _check_stack(s: RisleyNSettings, believed: bool) -> None:
    """Each prism alone must pass the on-axis beam, and the stack must pass it at every combination of prism
    angles without a back face reaching past the next prism's front face."""
    st = stack(s, believed)
    prefix = "believed_" if believed else ""
    field = f"risley_n.{prefix}apex_angle_deg"
    given = ",".join(f"{a:g}" for a in (s.believed(f"{prefix}apex_angle_deg") if believed else s.apex_angle_deg))
    for n_glass, apex in zip(st.n_glass, st.apex):
        critical = math.degrees(math.asin(1.0 / n_glass))
        if math.degrees(apex) >= critical:
            raise InputError(field, given, f"angles below {critical:.3f} deg for refractive index {n_glass:g} "
                                           f"(total internal reflection of the on-axis beam)")
    run = model.trace(st, np.array([0.0, 0.0, 1.0]), model.relative_angle_grid(s.prisms, GRID_SAMPLES))
    if run.reflected.any():
        raise InputError(field, given, "smaller angles: the prisms together reflect the on-axis beam totally at "
                                       "some prism angles")
    worst = run.overshoot.max(axis=0)
    if (worst > 0.0).any():
        gaps = tuple(g * 1e3 for g in st.gaps)
        need = ",".join(f"{(g + max(w, 0.0) * 1e3) * 1.05:.2f}" for g, w in zip(gaps, worst))
        raise InputError(f"risley_n.{prefix}gap_mm", ",".join(f"{g:g}" for g in gaps),
                         f"gaps of at least {need} mm: a tilted back face reaches past the next prism's front face "
                         f"where the on-axis beam crosses")


def _struct(st: model.Stack, turns, phase0_deg, encoder_arcsec, noise_arcsec: float):
    prisms = wedges.Prisms()
    pad = (0.0,) * (wedges.MAX_PRISMS - len(st.n_glass))
    prisms.count = len(st.n_glass)
    prisms.n_glass = wp.vec3d(*(tuple(st.n_glass) + (1.0,) * len(pad)))
    prisms.apex = wp.vec3d(*(tuple(st.apex) + pad))
    prisms.thickness = wp.vec3d(*(tuple(st.thickness) + pad))
    prisms.front = wp.vec3d(*(tuple(st.fronts) + pad))
    prisms.turns = wp.vec3d(*(tuple(float(m) for m in turns) + pad))
    prisms.phase0 = wp.vec3d(*(tuple(math.radians(p) + e * ARCSEC for p, e in zip(phase0_deg, encoder_arcsec)) + pad))
    prisms.encoder_sigma = noise_arcsec * ARCSEC
    return prisms


@register("deflector", "risley_n")
class RisleyNDeflector:
    """The prisms of ``[risley_n]`` (resolved settings) in front of an emitter."""

    settings = RisleyNSettings
    rigid_nominal = True  # the rigid-array (nominal) georeferencing model is defined for it

    @property
    def kernel(self):
        """The kernel side: its struct and device functions."""
        return wedges.RISLEY_N

    def __init__(self, s: RisleyNSettings, emitter):
        self.s = s
        self.emitter = emitter
        self.pattern_hz, self.turns = pattern(s)

    def timing(self) -> PulseTiming:
        """Pulses at prf_hz; the scan phase turns at the pattern frequency f_p from 0 at GPS time 0."""
        return PulseTiming(prf_hz=self.s.prf_hz, rotation_hz=self.pattern_hz, phase0_rad=0.0, field_prefix="risley_n")

    def params(self, believed: bool):
        s = self.s
        phase0 = s.expand("phase0_deg", s.phase0_deg)
        if believed:
            return _struct(stack(s, True), self.turns, phase0, (0.0,) * s.prisms, 0.0)
        return _struct(stack(s), self.turns, phase0, s.expand("encoder_arcsec", s.encoder_arcsec),
                       s.encoder_noise_arcsec)

    @property
    def believed_is_truth(self) -> bool:
        s = self.s
        return not (any(s.expand("encoder_arcsec", s.encoder_arcsec)) or s.encoder_noise_arcsec) and (
            stack(s, True) == stack(s))

    def _edge_beams(self) -> np.ndarray:
        """The emitter's beams that bound its fan (the extremes along x, y and both diagonals) and the central one."""
        d = self.emitter.directions()
        keys = (d[:, 0], d[:, 1], d[:, 0] + d[:, 1], d[:, 0] - d[:, 1])
        picks = {int(np.argmax(k)) for k in keys} | {int(np.argmin(k)) for k in keys} | {int(np.argmax(d[:, 2]))}
        return d[sorted(picks)]

    @functools.cached_property
    def _traced(self) -> tuple[float, float]:
        """(largest off-axis angle, largest angle between a true and a rigid-array direction) over the angle grid."""
        s = self.s
        beams = self._edge_beams()
        grid = model.relative_angle_grid(s.prisms, GRID_SAMPLES)
        st = stack(s)
        run = model.trace(st, beams[:, None, :], grid[None, :, :])
        center = model.trace(st, np.array([0.0, 0.0, 1.0]), grid)
        rigid = model.rigid_directions(beams[:, None, :], center.directions[None, :, :])
        off_axis = np.arctan2(np.hypot(run.directions[..., 0], run.directions[..., 1]), run.directions[..., 2])
        cross = np.linalg.norm(np.cross(run.directions, rigid), axis=-1)
        distortion = np.arctan2(cross, np.sum(run.directions * rigid, axis=-1))
        if not run.ok.any():
            return 0.0, 0.0
        return float(off_axis[run.ok].max()) + REACH_MARGIN_RAD, float(distortion[run.ok].max())

    def max_off_axis_rad(self) -> float:
        """Largest angle between an exiting beam and the axis [rad] (the fan's edge beams traced over the grid)."""
        return self._traced[0]

    def max_distortion_rad(self) -> float:
        """Largest angle between a beam's true and rigid-array exit directions [rad] (traced over the grid)."""
        return self._traced[1]

    def reach_deg(self) -> float:
        return math.degrees(self.max_off_axis_rad())

    def edge_buffer_m(self, altitude_m: float, divergence_mrad: float) -> float:
        """The automatic edge buffer [m]: the footprint and the rigid-array distortion at the slant range of the
        widest beam, h / cos θ_max · (divergence/2 + the largest distortion angle)."""
        slant = altitude_m / math.cos(min(self.max_off_axis_rad(), math.radians(80.0)))
        return slant * (0.5 * divergence_mrad * 1e-3 + self.max_distortion_rad())
