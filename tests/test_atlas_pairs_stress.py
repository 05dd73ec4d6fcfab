"""Bad input to ATLAS's beam pairs (``[pairs]``) is refused naming the field, one line and exit status 2 from the
command line with no file written; the pattern's angles and strong beams against ICESat-2's definitions; the beam
table kernel against the host's directions on every device."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

from flightsim.core.errors import InputError
from flightsim.engine.config import set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.instrument.pairs import GROUND_TRACKS, PairsEmitter, PairsSettings
from kernels import emitters

BAD = [
    ("pairs.pair_spacing_mrad", -6.6, "pairs.pair_spacing_mrad"),
    ("pairs.pair_spacing_mrad", 0.0, "pairs.pair_spacing_mrad"),
    ("pairs.beam_spacing_mrad", -0.18, "pairs.beam_spacing_mrad"),
    ("pairs.beam_spacing_mrad", 7.0, "pairs.beam_spacing_mrad"),  # wider than the pairs' spacing: pairs overlap
    ("pairs.energy_ratio", 0.0, "pairs.energy_ratio"),
    ("pairs.energy_ratio", -4.0, "pairs.energy_ratio"),
    ("pairs.energy_ratio", 0.25, "pairs.energy_ratio"),  # a "weak" beam stronger than its strong one
    ("pairs.energy_ratio", math.nan, "pairs.energy_ratio"),
    ("pairs.beams", "gt1l,gt4r", "pairs.beams"),
    ("pairs.beams", "gt1l,gt1l", "pairs.beams"),
    ("pairs.beams", "GT1L", "pairs.beams"),
    ("pairs.sc_orient", 2, "pairs.sc_orient"),  # transition: no science data
    ("pairs.sc_orient", -1, "pairs.sc_orient"),
]


@pytest.mark.parametrize("key,value,field", BAD)
def test_bad_pairs_settings_are_refused_naming_the_field(key, value, field):
    cfg = preset_config("atlas")
    with pytest.raises(InputError, match=field.replace(".", r"\.")):
        set_value(cfg, key, value)
        validate(cfg)


@pytest.mark.parametrize("setting", ["pairs.pair_spacing_mrad=-1", "pairs.energy_ratio=0", "pairs.beams=gt9x"])
def test_the_command_line_refuses_them_in_one_line_and_writes_nothing(tmp_path, setting):
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "flightsim", "simulate", "--instrument", "atlas", "--duration",
                           "0.001", "--set", setting, "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and setting.split("=")[0] in done.stderr
    assert not out.exists() or not any(out.iterdir())


def test_the_pattern_and_its_strong_beams_as_icesat2_defines_them():
    s = PairsSettings()
    e = PairsEmitter(s)
    assert e.beam_names == GROUND_TRACKS
    # left to right across the direction of flight; 90 m within a pair, 3.3 km between pairs at 500 km
    np.testing.assert_allclose(e.angles_mrad, [-6.69, -6.51, -0.09, 0.09, 6.51, 6.69], atol=1e-12)
    assert np.all(np.diff(e.angles_mrad) > 0)
    assert 500e3 * (math.tan(e.angles_mrad[1] * 1e-3) - math.tan(e.angles_mrad[0] * 1e-3)) == pytest.approx(90.0,
                                                                                                            abs=0.01)
    # backward (0): gt1l, gt2l, gt3l strong; forward (1): the right ones (ATL03's orbit_info/sc_orient)
    assert list(e.strong) == [True, False, True, False, True, False]
    np.testing.assert_allclose(e.energy_scale(), [1, 0.25, 1, 0.25, 1, 0.25])
    forward = PairsEmitter(PairsSettings(sc_orient=1, energy_ratio=2.0))
    assert list(forward.strong) == [False, True, False, True, False, True]
    np.testing.assert_allclose(forward.energy_scale(), [0.5, 1, 0.5, 1, 0.5, 1])
    some = PairsEmitter(PairsSettings(beams=("gt3r", "gt1l")))  # a subset, flown in ATL03's order
    assert some.beam_names == ("gt1l", "gt3r") and some.beams_per_pulse == 2


@wp.kernel
def _directions(table: emitters.BeamTable, out: wp.array(dtype=wp.vec3d)):
    b = wp.tid()
    out[b] = emitters.table_direction(b, table)


def test_the_beam_table_on_the_device_is_the_hosts(device):
    e = PairsEmitter(PairsSettings())
    out = wp.zeros(e.beams_per_pulse, dtype=wp.vec3d, device=device)
    wp.launch(_directions, e.beams_per_pulse, inputs=[e.params(device)], outputs=[out], device=device)
    theta = np.array([-6.69, -6.51, -0.09, 0.09, 6.51, 6.69]) * 1e-3  # float64 closed form
    expected = np.column_stack([np.zeros(6), np.sin(theta), np.cos(theta)])
    np.testing.assert_array_equal(out.numpy(), e.directions())
    np.testing.assert_allclose(out.numpy(), expected, rtol=0, atol=1e-15)


def test_the_weak_beams_echo_a_quarter_of_the_strong_ones_on_every_device(tmp_path, device):
    """Each beam's expected signal scaled by its share of the pulse energy in the photon kernel: without dead time
    the surface photons of a pair's strong and weak beams are Poisson with means in the ratio 4 (within 4σ)."""
    import h5py

    from flightsim.engine.run import simulate_to_directory

    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": 0.01, "photon.reflectance": 0.9, "photon.dead_time_s": 0.0,
                       "photon.max_events": 128, "photon.gate_m": [499850.0, 500150.0], "run.device": device}.items():
        set_value(cfg, key, value)
    simulate_to_directory(validate(cfg), tmp_path / "run")
    with h5py.File(tmp_path / "run" / "photons.h5") as f:
        pixel, signal = f["photons/pixel"][:], f["photons/signal"][:]
    for strong_beam in (0, 2, 4):
        strong = int(((pixel == strong_beam) & (signal == 1)).sum())
        weak = int(((pixel == strong_beam + 1) & (signal == 1)).sum())
        ratio = strong / weak
        assert abs(ratio - 4.0) < 4.0 * ratio * math.sqrt(1.0 / strong + 1.0 / weak), (strong_beam, strong, weak)
