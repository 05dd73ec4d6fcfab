"""The received power of waveforms over a point cloud (``flightsim.engine.readouts.waveforms._to_power``), worked out
in pieces of rows on threads: every row the one the link equation gives for that row alone."""
from __future__ import annotations

import numpy as np

C = 299_792_458.0


class _Detector:
    def pulse_energy_j(self) -> float:
        return 2.3e-3

    def link_m2(self) -> float:
        return 7.1e-4


def test_power_in_pieces_on_threads_is_each_rows_own(monkeypatch):
    from flightsim.core import process_map
    from flightsim.engine.readouts import waveforms

    monkeypatch.setattr(process_map, "usable_cores", lambda: 4)
    monkeypatch.setattr(waveforms, "POWER_ROWS", 3)
    rng = np.random.default_rng(7)
    k, n, dt, rho = 41, 300, 1e-9, (0.4, 0.57)
    w = {name: rng.uniform(0.0, 2e-3, (k, n)).astype(np.float32) for name in ("rx", "ground", "canopy")}
    w["ground"][5], w["canopy"][5] = 0.0, 0.0  # no echo: no power, no mean height
    w["outside"] = np.zeros(k, dtype=bool)
    w["outside"][9] = True
    r, z0, first, dz = rng.uniform(480e3, 520e3, k), rng.uniform(0.0, 30.0, k), rng.uniform(10.0, 20.0, k), -0.999
    power, received = waveforms._to_power(_Detector(), w, r, (z0, first, dz), rho, dt)
    assert power.dtype == np.float32 and power.shape == (k, n) and received.shape == (k, 4)
    for i in range(k):  # one row at a time, the equation as its docstring writes it
        rx = w["rx"][i].astype(np.float64)
        e_g, e_c = w["ground"][i].sum(dtype=np.float64), w["canopy"][i].sum(dtype=np.float64)
        made = e_g + e_c > 0.0 and not w["outside"][i]
        if not made:
            assert not power[i].any() and np.array_equal(received[i], [0.0, 0.0, 0.0, 0.0]), i
            continue
        total = e_g + e_c
        rho_mean = 1.0 / (e_g / total / rho[0] + e_c / total / rho[1])
        scale = 2.3e-3 * 7.1e-4 * rho_mean / r[i] ** 2 * 0.5 * C
        heights = z0[i] + (first[i] + 0.5 * C * dt * np.arange(n)) * dz
        inside = rx.sum() * 0.5 * C * dt
        assert np.array_equal(power[i], (rx * scale).astype(np.float32)), i
        assert np.array_equal(received[i], [inside, max(1.0 - inside, 0.0), (rx * heights).sum() / rx.sum(), 1.0]), i
