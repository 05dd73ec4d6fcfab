"""ATL03-style signal confidence from height histograms (flightsim.scoring.signal_finder): against the
simulator's truth on a pass with a known background rate, and on pure noise drawn here."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from flightsim.core.process_map import ProcessMap
from flightsim.engine.config import set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.engine.run import simulate_to_directory
from flightsim.instrument.pairs import SINGLE_BEAM
from scipy.stats import poisson

from flightsim.core.poisson import at_least
from flightsim.scoring.signal_finder import HIGH, LOW, SignalFinder, _shots, along_spread


def _pass(tmp_path, **settings) -> tuple[np.ndarray, np.ndarray]:
    """(signal_conf_ph, truth_kind) of a 0.1 s atlas pass (1000 shots) in a 300 m telemetry band."""
    cfg = preset_config("atlas")
    for key, value in {**SINGLE_BEAM, "flight.duration_s": 0.1, "photon.max_events": 64, "photon.gate_m": [499850.0, 500150.0],
                       **settings}.items():
        set_value(cfg, key, value)
    simulate_to_directory(validate(cfg), tmp_path / "p")
    with h5py.File(tmp_path / "p" / "atl03.h5") as f:
        return f["gt1/heights/signal_conf_ph"][:, 0], f["gt1/heights/truth_kind"][:]


def test_confidence_against_the_truth_of_a_pass_with_a_known_background(tmp_path):
    """3 MHz of background (0.02 photons per m and shot, 6 per shot in the band) and ~1 surface photon per
    shot: measured 99.3 % of high-confidence photons are the surface's (the rest is the background inside
    its ±0.5 m), and every surface photon gets confidence ≥ 2."""
    conf, kind = _pass(tmp_path, **{"photon.noise_hz": 3.0e6})
    assert (kind > 0).sum() > 500 and (kind == 0).sum() > 4000
    assert (kind[conf == HIGH] > 0).mean() >= 0.95
    assert (conf[kind == 1] >= LOW).mean() >= 0.90


def test_weak_signal_keeps_its_precision(tmp_path):
    """A dark surface (0.26 signal photons per shot) in the same background: measured 95 % precision of the
    high confidence and 91 % of surface photons ≥ 2; thresholds 90 % and 85 %."""
    conf, kind = _pass(tmp_path, **{"photon.noise_hz": 3.0e6, "photon.reflectance": 0.02, "flight.duration_s": 0.2})
    assert (kind[conf == HIGH] > 0).mean() >= 0.90
    assert (conf[kind == 1] >= LOW).mean() >= 0.85


def test_a_count_at_or_below_its_poisson_mean_has_a_tail_of_at_least_one_half():
    """The finder computes P(K ≥ k) only for counts above their mean: at or below it the tail is ≥ 1/2 (a Poisson
    median is at least λ − ln 2), against SciPy's survival function over means from 1e-3 to 1e4, at the integers just
    below each mean where the tail is least; and the shortcut's values where it computes them."""
    from flightsim.scoring.signal_finder import _tail_above_mean

    lam = np.concatenate([np.geomspace(1e-3, 1e4, 20_000), np.arange(1, 200) + 1e-9, np.arange(1, 200) - 1e-9])
    k = np.floor(lam)
    assert (poisson.sf(k - 1, lam) >= 0.5).all()
    rng = np.random.default_rng(2)
    counts, means = rng.integers(0, 40, 5_000), rng.uniform(0.0, 30.0, 5_000)
    tail = _tail_above_mean(counts, means)
    above = counts > means
    assert np.array_equal(tail[above], at_least(counts[above], means[above])) and (tail[~above] == 1.0).all()
    assert 0 < above.sum() < len(above)


@pytest.mark.parametrize("seed", range(4))
def test_distinct_shots_of_every_window_of_segments(seed):
    """The finder's shot counts (a segment's, and a pool's of segments lo … hi − 1) against ``np.unique`` of the
    pulses there: pulses whose photons span two or three segments, empty segments, a pulse seen again later."""
    rng = np.random.default_rng(seed)
    pulse = np.sort(rng.integers(0, 300, 2_000))
    segment = np.sort(np.clip(pulse // 7 + rng.integers(-1, 2, len(pulse)), 0, None))  # pulses across boundaries
    segment[segment == 13] = 14  # an empty segment
    pulse[-5:] = pulse[0]  # a shot's photon in its segment and again far later
    came, bounds = _shots(segment, pulse)
    m = int(segment[-1]) + 1
    for lo in range(m):
        for hi in range(lo + 1, min(m, lo + 6) + 1):
            expected = len(np.unique(pulse[(segment >= lo) & (segment < hi)]))
            assert np.count_nonzero(came[bounds[lo]:bounds[hi]] < lo) == expected, (lo, hi)
        assert bounds[lo + 1] - bounds[lo] == len(np.unique(pulse[segment == lo]))


def _reference(finder: SignalFinder, along, h, pulse) -> np.ndarray:
    """The ATBD's steps photon by photon, in plain float64 loops (the module docstring's definitions): ranges as closed
    intervals around each height, shots as the distinct pulse ids."""
    inner, outer, half = finder.window_m, finder.background_m / 2.0, finder.window_m / 2.0
    segment = np.floor(along / finder.segment_m).astype(np.int64)
    conf = np.zeros(len(h), dtype=np.int64)
    for j in np.unique(segment):
        mine = np.flatnonzero(segment == j)
        pool = np.abs(segment - j) <= finder.background_segments
        ph, band = h[pool], (h[pool].min(), h[pool].max())
        for i in mine:
            ring = np.count_nonzero((ph >= h[i] - outer) & (ph <= h[i] + outer)) - np.count_nonzero(
                (ph >= h[i] - inner) & (ph <= h[i] + inner))
            length = sum(max(min(b, band[1]) - max(a, band[0]), 0.0)
                         for a, b in ((h[i] - outer, h[i] - inner), (h[i] + inner, h[i] + outer)))
            beta = ring / max(length, finder.window_m) / len(set(pulse[pool].tolist()))
            others = np.count_nonzero((h[mine] >= h[i] - half) & (h[mine] <= h[i] + half)) - 1
            p = poisson.sf(others - 1, beta * len(set(pulse[mine].tolist())) * finder.window_m)
            conf[i] = HIGH if p < finder.p_high else 3 if p < finder.p_medium else LOW if p < finder.p_low else 0
        signal = h[mine][conf[mine] >= LOW]
        for i in mine:
            if conf[i] == 0 and len(signal) and np.abs(signal - h[i]).min() <= finder.window_m:
                conf[i] = 1
    return conf


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("finder", [SignalFinder(), SignalFinder(p_low=0.5, p_medium=0.2, p_high=0.05),
                                    SignalFinder(p_low=0.8, p_medium=0.5, p_high=0.2)], ids=["atbd", "loose", "looser"])
def test_confidence_against_the_steps_photon_by_photon(seed, finder):
    """``classify`` against :func:`_reference` on 3,000 photons: a surface in noise over 25 segments, pulses whose
    photons span two segments, a gap of empty segments, noise heights on a grid of 0.25 m (ties exactly at the
    windows' edges); with loose thresholds most noise photons' tails lie near one, so a count or a shot off by one
    changes some confidence."""
    rng = np.random.default_rng(seed)
    pulse = np.sort(rng.integers(0, 600, 3_000))
    along = pulse * 0.8 + rng.uniform(0.0, 0.5, len(pulse))
    along[(along > 200.0) & (along < 245.0)] += 60.0  # empty segments between
    h = np.where(rng.random(len(pulse)) < 0.3, 40.0 + rng.normal(0.0, 0.15, len(pulse)),
                 np.round(rng.uniform(0.0, 120.0, len(pulse)) * 4.0) / 4.0)
    assert np.array_equal(finder.classify(along, h, pulse), _reference(finder, along, h, pulse))


def test_pure_noise_gets_no_high_confidence():
    """Uniform background drawn here: 2000 shots 0.7 m apart, 6 photons per shot over a 300 m band. Low
    confidence (p < 1.35e-3, from ~12,000 tests) comes up a few times by chance; high (p < 2.9e-7) not."""
    rng = np.random.default_rng(5)
    counts = rng.poisson(6.0, 2000)
    pulse = np.repeat(np.arange(2000), counts)
    conf = SignalFinder().classify(pulse * 0.7, rng.uniform(0.0, 300.0, pulse.size), pulse)
    assert (conf == HIGH).sum() == 0
    assert (conf >= LOW).mean() < 0.01


def test_a_surface_drawn_here_is_found_where_it_is():
    """A surface sloping 5 % along track, 1 photon per shot with 10 cm of spread, in 3 MHz-like noise (6 per
    shot over 300 m): the noise within ±0.5 m of the surface is 2 % of its photons."""
    rng = np.random.default_rng(6)
    shots = np.arange(3000)
    noise = rng.poisson(6.0, shots.size)
    pulse = np.concatenate([shots, np.repeat(shots, noise)])
    along = pulse * 0.7
    surface = 100.0 + 0.05 * along[:shots.size] + rng.normal(0.0, 0.1, shots.size)
    h = np.concatenate([surface, rng.uniform(0.0, 300.0, noise.sum())])
    conf = SignalFinder().classify(along, h, pulse)
    truth = np.arange(pulse.size) < shots.size
    assert (truth[conf == HIGH]).mean() >= 0.95 and (conf[truth] >= LOW).mean() >= 0.95


@pytest.mark.parametrize("processes", [0, 2])
def test_classifying_block_by_block_equals_classifying_at_once(processes):
    """Blocks of 1000 photons read with their neighbours, in this process or two blocks at a time on two worker
    processes: every confidence the same as the whole pass classified at once."""
    rng = np.random.default_rng(7)
    pulse = np.repeat(np.arange(4000), rng.poisson(5.0, 4000))
    along, h = pulse * 0.7, np.where(rng.random(pulse.size) < 0.2, 50.0 + rng.normal(0, 0.1, pulse.size),
                                     rng.uniform(0.0, 300.0, pulse.size))
    finder = SignalFinder()
    out = np.full(pulse.size, -1, dtype=np.int8)
    written = []

    def write(lo, values):
        out[lo:lo + len(values)] = values
        written.append(lo)

    workers = ProcessMap(processes) if processes else None
    try:
        finder.classify_stream(pulse.size, lambda lo, hi: (along[lo:hi], h[lo:hi], pulse[lo:hi]), write, block=1000,
                               workers=workers)
    finally:
        if workers is not None:
            workers.stop()
    assert written == list(range(0, pulse.size, 1000))
    assert np.array_equal(out, finder.classify(along, h, pulse))


def test_blocks_of_a_slanted_beam_classify_as_the_whole_pass():
    """Off nadir a shot's photons lie along track in the order of their heights (here up to ±75 m: a wide window at a
    large angle), so a photon stored before a block's first row can lie far ahead of it: blocks read only a fixed
    distance beyond their edge rows (before) classified 70 of these photons otherwise than the whole pass; read as far
    as the stream's spread requires, every block as the whole pass."""
    finder = SignalFinder()
    for seed in range(6):
        rng = np.random.default_rng(seed)
        pulse = np.repeat(np.arange(4000), rng.poisson(5.0, 4000))
        h = np.where(rng.random(pulse.size) < 0.2, 50.0 + rng.normal(0, 0.1, pulse.size),
                     rng.uniform(0.0, 300.0, pulse.size))
        along = pulse * 0.7 + (h - 150.0) * 0.5
        whole = finder.classify(along, h, pulse)
        for block in (300, 1000, 1700):
            out = np.full(pulse.size, -1, dtype=np.int8)
            finder.classify_stream(pulse.size, lambda lo, hi: (along[lo:hi], h[lo:hi], pulse[lo:hi]),
                                   lambda lo, values: out.__setitem__(slice(lo, lo + len(values)), values), block=block)
            assert np.array_equal(out, whole), (seed, block)


def test_along_spread_is_the_largest_inversion_over_parts():
    """along_spread over parts in turn, the furthest distance carried: max over i < j of a[i] − a[j] of the whole
    array (pairs by brute force, non-finite distances left out), 0 for a sorted one."""
    rng = np.random.default_rng(4)
    a = np.cumsum(rng.uniform(0.0, 1.0, 300)) + rng.normal(0.0, 5.0, 300)
    a[rng.choice(300, 20, replace=False)] = np.nan
    finite = a[np.isfinite(a)]
    expected = max(0.0, max(finite[i] - finite[j] for i in range(len(finite)) for j in range(i + 1, len(finite))))
    spread, furthest = 0.0, -np.inf
    for part in np.array_split(a, 7):
        found, furthest = along_spread(part, furthest)
        spread = max(spread, found)
    assert spread == expected and furthest == finite.max()
    assert along_spread(np.sort(finite))[0] == 0.0 and along_spread(np.array([np.nan]))[0] == 0.0


def test_photons_without_a_position_are_noise_and_nobodys_neighbours():
    """Non-finite heights or distances (a photon without a position): those photons 0, every other photon as if they
    were not there (before, one NaN height in a pool made every confidence 0)."""
    rng = np.random.default_rng(2)
    pulse = np.sort(rng.integers(0, 3_000, 20_000))
    along = pulse * 0.7 + rng.uniform(0.0, 0.3, len(pulse))
    h = np.where(rng.random(len(pulse)) < 0.3, 40.0 + rng.normal(0.0, 0.2, len(pulse)),
                 rng.uniform(0.0, 300.0, len(pulse)))
    lost = rng.random(len(h)) < 0.05
    h[lost & (rng.random(len(h)) < 0.7)] = np.nan
    along[lost & np.isfinite(h)] = np.inf
    conf = SignalFinder().classify(along, h, pulse)
    assert (conf[lost] == 0).all()
    assert np.array_equal(conf[~lost], SignalFinder().classify(along[~lost], h[~lost], pulse[~lost]))
    assert np.count_nonzero(conf[~lost] >= LOW) > 1_000  # the surface is found
