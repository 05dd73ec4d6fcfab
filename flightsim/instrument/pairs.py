"""ATLAS's beam pairs (``instrument.emitter = "pairs"``, ``[pairs]``): one pulse split into six beams in three pairs,
each pair a strong and a weak beam, named by their ICESat-2 ground tracks gt1l, gt1r, gt2l, gt2r, gt3l, gt3r (left
to right across the direction of flight, pair 2 on the reference ground track).

Pair k (1, 2, 3) is centred (k − 2)·``pair_spacing_mrad`` across track, its left and right beams ∓
``beam_spacing_mrad``/2 from that centre (emitter +y: to the right of flight with the sensor's default boresight).
Which beam of a pair is strong follows the spacecraft's orientation as ATL03 defines ``orbit_info/sc_orient``:
0 backward, the left beams strong (ATLAS spots 1, 3, 5 on gt1l, gt2l, gt3l); 1 forward, the right beams strong
(spots 1, 3, 5 on gt3r, gt2r, gt1r). The strong beam carries ``photon.pulse_energy_j``, the weak one that divided by
``energy_ratio``. The pattern's along-track stagger (ATLAS: 2.5 km within a pair) is not modelled: every beam of a
pulse lies on one across-track line.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from kernels import emitters

GROUND_TRACKS = ("gt1l", "gt1r", "gt2l", "gt2r", "gt3l", "gt3r")
MAX_SPACING_MRAD = 100.0
# overrides of the atlas preset that fly the one nadir strong beam it flew before its six (ground track "gt1")
SINGLE_BEAM = {"instrument.emitter": "fan", "fan.array": 1, "fan.divergence_mrad": 0.024}


@dataclass
class PairsSettings(Settings):
    """Three pairs of a strong and a weak beam, ATLAS's pattern."""

    beams: tuple[str, ...] = setting(GROUND_TRACKS, "the ground tracks flown (ATL03 names)", choices=GROUND_TRACKS)
    pair_spacing_mrad: float = setting(6.6, "across-track angle between the centres of neighbouring pairs", "mrad",
                                       range=(0.0, MAX_SPACING_MRAD), lo_open=True)
    beam_spacing_mrad: float = setting(0.18, "across-track angle between the two beams of a pair", "mrad",
                                       range=(0.0, MAX_SPACING_MRAD), lo_open=True)
    energy_ratio: float = setting(4.0, "pulse energy of a strong beam over a weak one's", "",
                                  range=(1.0, 1000.0))
    sc_orient: int = setting(0, "spacecraft orientation as ATL03's orbit_info/sc_orient: 0 backward (left beams "
                             "strong), 1 forward (right beams strong)", range=(0, 1))
    divergence_mrad: float = setting(0.024, "full divergence angle of each beam (sizes the footprint)", "mrad",
                                     range=(0.0, 100.0))

    def check(self, context) -> None:
        if len(set(self.beams)) != len(self.beams):
            raise InputError("pairs.beams", ",".join(self.beams), "distinct ground tracks from "
                             + ", ".join(GROUND_TRACKS))
        if not self.beam_spacing_mrad < self.pair_spacing_mrad:
            raise InputError("pairs.beam_spacing_mrad", self.beam_spacing_mrad,
                             f"an angle below pairs.pair_spacing_mrad = {self.pair_spacing_mrad:g} mrad "
                             "(the pairs must not overlap)")


def across_track_mrad(name: str, pair_spacing_mrad: float, beam_spacing_mrad: float) -> float:
    """Across-track angle of ground track ``name`` (gt1l … gt3r) from the pattern's centre, + right [mrad]."""
    pair, side = int(name[2]), name[3]
    return (pair - 2) * pair_spacing_mrad + (-0.5 if side == "l" else 0.5) * beam_spacing_mrad


def is_strong(name: str, sc_orient: int) -> bool:
    """Whether ground track ``name`` is a strong beam: the left ones backward (0), the right ones forward (1)."""
    return name[3] == ("l" if sc_orient == 0 else "r")


@register("emitter", "pairs")
class PairsEmitter:
    """The beams of ``[pairs]``; beam b is ``beam_names[b]`` (in ATL03's order gt1l … gt3r)."""

    settings = PairsSettings
    kernel = emitters.TABLE  # the kernel side: its struct and device functions
    beam_columns = 2  # LAS beam_row = the pair's index in the beams flown // 2 (gt1, gt2, gt3 when all fly)

    def __init__(self, s: PairsSettings):
        self.beam_names = tuple(sorted(s.beams, key=GROUND_TRACKS.index))
        self.sc_orient = s.sc_orient
        self.divergence_mrad = s.divergence_mrad
        self.angles_mrad = np.array([across_track_mrad(n, s.pair_spacing_mrad, s.beam_spacing_mrad)
                                     for n in self.beam_names])
        self.strong = np.array([is_strong(n, s.sc_orient) for n in self.beam_names])
        self.energy_ratio = s.energy_ratio

    @property
    def beams_per_pulse(self) -> int:
        return len(self.beam_names)

    @property
    def half_diagonal_rad(self) -> float:
        return float(np.abs(self.angles_mrad).max()) * 1e-3

    def energy_scale(self) -> np.ndarray:
        """Each beam's pulse energy over ``photon.pulse_energy_j`` (the strong beam's): 1 strong, 1/ratio weak."""
        return np.where(self.strong, 1.0, 1.0 / self.energy_ratio)

    def directions(self) -> np.ndarray:
        """(beams, 3) unit directions (0, sin θ, cos θ) in the emitter frame, θ the across-track angle."""
        theta = self.angles_mrad * 1e-3
        return np.stack([np.zeros_like(theta), np.sin(theta), np.cos(theta)], axis=-1)

    def params(self, device: str):
        table = emitters.BeamTable()
        table.directions = wp.array(self.directions(), dtype=wp.vec3d, device=device)
        return table
