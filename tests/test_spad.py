"""The small-body SPAD lidar end to end: one MODE-B dwell gridded into points and scored against the sandbox."""
from __future__ import annotations

import pytest

from flightsim.studies.spad import frame_config, run_frame
from flightsim.engine.readouts.photons import Photons


def test_one_mode_b_dwell_gives_a_point_per_beam_at_the_pile_up_bias():
    r = run_frame(frame_config(63.0, "B", "cpu", 1720), "MODE-B 63 m, one step", 160)
    assert r.cells_filled == 1024  # every beam's spot becomes one point of the 160 × 160 grid
    assert 0.5 < r.signal_per_shot < 1.0
    # ~1600 photons per point: the spread is the sandbox under a 4.5 cm cell, far below the paper's 3 cm
    assert r.accuracy_3sigma_cm < 1.5
    assert r.bias_cm == pytest.approx(r.expected_bias_cm, abs=0.5)


def _photons(cfg, on_device):
    """Every photon of a run as (time of flight, signal flag) arrays in launch order."""
    import numpy as np

    from flightsim.studies.spad import frame_simulator

    _, sim = frame_simulator(cfg)
    parts = []
    if on_device:
        sim.run(Photons(on_device=True),
                lambda f: parts.append((f.time_of_flight_s.numpy().copy(), f.signal.numpy().astype(bool))))
    else:
        sim.run(Photons(), lambda c: parts.append((c.time_of_flight_s, c.signal)))
    return tuple(np.concatenate([p[k] for p in parts]) for k in (0, 1))


def test_photons_are_the_same_on_the_device_and_on_the_host_whatever_the_chunks():
    import numpy as np

    from flightsim.engine.config import validate

    cfg = frame_config(100.0, "A", "cpu", 12)
    cfg.photon.noise_hz = 2e6  # ~8 background arrivals per gate: beyond the flat buffers' first size
    cfg = validate(cfg)
    host = _photons(cfg, on_device=False)
    assert len(host[0]) > 3 * 12 * 1024
    device = _photons(cfg, on_device=True)
    cfg.run.chunk_pulses = 5
    split = _photons(validate(cfg), on_device=True)
    for a, b in ((host, device), (host, split)):
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
