"""Corner-cube calibration of a simulated spaceborne pass (the atlas preset over a CCR field, photons traced
on the device): both of the seed patent's estimators recover the injected pointing and ranging biases."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from flightsim.calibration.geolocation import Bias
from flightsim.studies.spaceborne import simulate_pass

TRUTH = Bias(3.0, -2.0, 0.25)


@functools.lru_cache(maxsize=None)
def _pass():
    return simulate_pass(TRUTH)


def test_ccr_photons_come_back_on_the_simulated_pass():
    p = _pass()
    assert (p.kind == 2).sum() > 200
    assert len(p.patent.identification.tracks) >= 10  # the field is designed for 16 triggered CCRs


@pytest.mark.parametrize("method", ["patent", "least_squares"])
def test_pointing_bias_is_recovered_to_a_fifth_of_an_arcsecond(method):
    bias = getattr(_pass(), method).bias
    assert abs(bias.along_arcsec - TRUTH.along_arcsec) <= 0.2
    assert abs(bias.across_arcsec - TRUTH.across_arcsec) <= 0.2


def test_ranging_bias_is_recovered_once_the_ccr_pile_up_is_taken_out():
    p = _pass()
    bias, sigma = p.range_bias_m
    assert abs(bias - TRUTH.range_m) <= 0.02
    assert sigma < 0.01
    # without the correction the first photon of each CCR echo reads short: the estimate falls low
    assert TRUTH.range_m - p.least_squares.bias.range_m > 3 * sigma


@pytest.mark.parametrize("truth", ["3,-2", "a,b,c", "3,-2,nan", "100,0,0"])
def test_bad_truth_exits_2_naming_it(tmp_path, capsys, truth):
    from flightsim.cli import main

    assert main(["calibrate", "--truth", truth, "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "--truth" in err and "Traceback" not in err


def test_calibration_from_the_orbit_platform_with_per_shot_geometry():
    """The same field from a circular 500 km pass (the nadir turns ~0.5 mrad over the track): the
    calibration takes each shot's believed position and axes from the simulator."""
    p = simulate_pass(TRUTH, platform="orbit")
    assert p.track.shot_axes is not None
    bias = p.least_squares.bias
    assert abs(bias.along_arcsec - TRUTH.along_arcsec) <= 0.2
    assert abs(bias.across_arcsec - TRUTH.across_arcsec) <= 0.2
    assert abs(p.range_bias_m[0] - TRUTH.range_m) <= 0.02


def test_every_beam_of_the_six_is_calibrated_strong_and_weak():
    """The atlas preset's six beams over a CCR field each: every beam recovers the shared boresight and ranging
    biases; the weak beams (a quarter of the energy) see fewer CCR photons and calibrate less tightly."""
    from flightsim.studies.spaceborne import simulate_beams

    beams = simulate_beams(TRUTH)
    assert list(beams) == ["gt1l", "gt1r", "gt2l", "gt2r", "gt3l", "gt3r"]
    for name, p in beams.items():
        assert not isinstance(p, Exception), (name, p)
        limit = 0.2 if name.endswith("l") else 0.3  # backward orientation: the left beams are strong
        bias = p.least_squares.bias
        assert abs(bias.along_arcsec - TRUTH.along_arcsec) <= limit, name
        assert abs(bias.across_arcsec - TRUTH.across_arcsec) <= limit, name
        assert abs(p.range_bias_m[0] - TRUTH.range_m) <= 0.02, name
    for pair in ("gt1", "gt2", "gt3"):
        strong, weak = ((beams[f"{pair}{side}"].kind == 2).sum() for side in "lr")
        assert weak < 0.7 * strong, (pair, strong, weak)


def test_worker_processes_calibrate_the_beams_to_the_same_bits():
    """The sweep's beams calibrated by worker processes (as `flightsim calibrate` does on more than one core) give
    what the same calibrations give in this process, bit for bit; a beam whose calibration found too little comes
    back as its error, whole."""
    from flightsim.core.errors import InputError
    from flightsim.core.process_map import ProcessMap, map_rows
    from flightsim.studies import spaceborne

    names, beams = spaceborne._fly_beams(TRUTH, 16, "cpu", 0, 1.0e6, "lines")
    track, field, shot, range_m, *rest = beams[0].arguments()
    empty = (track, field, shot[:0], range_m[:0], *rest)  # no photons at all
    chunks = [*(beam.arguments() for beam in beams), empty]
    here = map_rows(spaceborne._calibrate_beam, chunks, None)
    workers = ProcessMap(2, ("flightsim.studies.spaceborne",))
    try:
        there = map_rows(spaceborne._calibrate_beam, iter(chunks), workers)
    finally:
        workers.stop()
    for name, beam, a, b in zip(names, beams, here, there):
        a, b = beam.calibrated(a), beam.calibrated(b)
        assert (a.least_squares.bias, a.patent.bias, a.range_bias_m) == (b.least_squares.bias, b.patent.bias,
                                                                           b.range_bias_m), name
        np.testing.assert_array_equal(a.least_squares.covariance, b.least_squares.covariance)
    assert isinstance(here[-1], InputError) and isinstance(there[-1], InputError)
    assert (there[-1].field, str(there[-1])) == (here[-1].field, str(here[-1]))
