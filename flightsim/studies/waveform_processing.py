"""Waveform ranging on the device against the host: the batched kernels (:mod:`flightsim.instrument.waveform_batch`)
against the float64 reference model's per-waveform NumPy/SciPy path (:func:`~flightsim.instrument.waveform_model.measure`,
``decompose``: gaussian_filter1d, find_peaks, curve_fit), over the waveforms of simulated runs (the change1 preset
over flat, 0.20-slope and bump scenes; the GEDI preset over its plane and over the test point-cloud forest) and
synthetic sums of 1-4 Gaussians with noise; and the waveforms per second of each path on the same chunk.

    python3 -m flightsim.studies.waveform_processing --device cpu            # the comparison table
    python3 -m flightsim.studies.waveform_processing --device cuda --time    # waveforms/s, host vs device

The fit's agreement is judged by the fit's own conditioning: near a least-squares optimum p_d (gradient zero, or
pointing out of the bounds), SSR(p) − SSR(p_d) ≈ ½ΔpᵀHΔp, Δp = p − p_d, H the SSR's Hessian at p_d (2JᵀJ plus the
residuals' curvature term, which noise makes matter). So where scipy's parameters p_s and the device's p_d differ, the
gap of scipy's SSR over the device's must account for q = ½ΔpᵀHΔp: the column ``q / bound`` is ≤ 1 where it does,
bound = 2 gap + 1e-9 SSR + ½ Σ_i |H_ii| (4 u_i)² (the factor 2 and 1e-9 of scipy's SSR: room for the quadratic
model's error and for the SSR's rounding; u_i: the spacing of parameter i as stored, in fit units: a component's time
t is stored in seconds, so its μ = (t − t0)/σ carries ulp(t)/σ), with the device's SSR at most scipy's (1 + 1e-9).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from flightsim.instrument import waveform_model as model
from flightsim.instrument.waveform_batch import process

CLOUD = Path(__file__).resolve().parents[2] / "tests" / "data" / "cloud_plot.laz"  # 35 m × 35 m, EPSG:32648
SSR_SLACK = 1e-9  # the device's SSR may exceed scipy's by this share; so may the parameters' ΔpᵀJᵀJΔp beyond the gap
ROUNDING_ULPS = 4.0  # the components are stored as times [s], amplitudes [W], σ [s]: each rounded to its ulp
FOREST_CENTRES = [(409011.0 + 6.5 * i, 3393011.0 + 6.5 * j) for i in range(3) for j in range(3)]


def simulated(name: str, device: str, instrument: str = "change1", scene: str = "flat",
              footprints: list | None = None, **settings) -> tuple[str, model.WaveformSystem, np.ndarray, np.ndarray]:
    """(name, system, t0 (W,) [s], waveforms (W, N) [W]) of one simulated run's waveforms.h5."""
    import h5py

    from flightsim.engine.run import simulate_to_directory
    from flightsim.instrument.waveform import system
    from flightsim.studies.waveform import waveform_config

    with tempfile.TemporaryDirectory() as tmp:
        csv = None
        if footprints:
            csv = Path(tmp) / "footprints.csv"
            csv.write_text("x,y,delta_time\n" + "".join(f"{x!r},{y!r},{1e8 + i}\n" for i, (x, y) in enumerate(footprints)))
        cfg = waveform_config(scene, device, None, instrument, str(csv) if csv else None, **settings)
        simulate_to_directory(cfg, Path(tmp) / "run")
        with h5py.File(Path(tmp) / "run" / "waveforms.h5") as f:
            g = f["BEAM0000"]
            n = int(g["rx_sample_count"][0])
            rx = g["rxwaveform"][:].reshape(-1, n)
            t0 = g["rx_window_start_s"][:]
    return name, system(cfg.waveform), t0, rx.astype(np.float64)


def synthetic(name: str, system: model.WaveformSystem, waveforms: int, samples: int, seed: int,
              noise: float = 0.01) -> tuple[str, model.WaveformSystem, np.ndarray, np.ndarray]:
    """Sums of 1-4 Gaussians (amplitudes 0.3-1 W, σ 1-3 pulse σ, centres in the middle 60 % of the window) plus
    Gaussian noise of ``noise`` W, rounded to float32 as a run's waveforms are."""
    rng = np.random.default_rng(seed)
    dt, sigma = system.sample_interval_s, model.pulse_sigma_s(system)
    t0 = 1.3e-3 + dt * rng.integers(0, 10 ** 6, waveforms)
    times = t0[:, None] + dt * np.arange(samples)[None, :]
    echo = rng.normal(0.0, noise, (waveforms, samples))
    for w in range(waveforms):
        for _ in range(rng.integers(1, 5)):
            centre = times[w, 0] + rng.uniform(0.2, 0.8) * samples * dt
            echo[w] += rng.uniform(0.3, 1.0) * np.exp(-0.5 * ((times[w] - centre) / (sigma * rng.uniform(1, 3))) ** 2)
    return name, system, t0, echo.astype(np.float32).astype(np.float64)


def waveform_sets(device: str = "cpu", quick: bool = False) -> list[tuple]:
    """The comparison's waveform sets (``quick``: fewer of each)."""
    shots = {"fixed.prf_hz": 20.0, "flight.duration_s": 0.1 if quick else 0.2}
    gedi_system = model.WaveformSystem(pulse_fwhm_s=1.5e-8, sample_interval_s=1e-9)
    change1_system = model.WaveformSystem(sample_interval_s=5e-11)
    sets = [simulated(f"change1 {scene}", device, "change1", scene, **shots) for scene in ("flat", "slope", "bump")]
    sets.append(simulated("gedi plane", device, "gedi", "flat", **{"flight.duration_s": 0.05 if quick else 0.2}))
    sets.append(simulated("gedi forest (cloud_plot.laz)", device, "gedi", str(CLOUD),
                          FOREST_CENTRES[:4] if quick else FOREST_CENTRES))
    sets.append(synthetic("synthetic, GEDI σ and Δt", gedi_system, 40 if quick else 400, 1000, 1))
    sets.append(synthetic("synthetic, change1 σ", change1_system, 10 if quick else 60, 4096, 2))
    return sets


def host_path(system: model.WaveformSystem, t0: np.ndarray, echo: np.ndarray):
    """The host's measures, peaks (scipy, as decompose finds them) and components, waveform by waveform."""
    from scipy.ndimage import gaussian_filter1d
    from scipy.signal import find_peaks

    times = t0[:, None] + system.sample_interval_s * np.arange(echo.shape[1])[None, :]
    sigma = model.pulse_sigma_s(system)
    measures, peaks, parts = [], [], []
    for w in range(len(echo)):
        measures.append(model.measure(system, times[w], echo[w]))
        smooth = gaussian_filter1d(echo[w], sigma / (times[w, 1] - times[w, 0]))
        peaks.append(find_peaks(smooth, prominence=0.05 * smooth.max())[0])
        parts.append(model.decompose(system, times[w], echo[w]))
    return times, measures, peaks, parts


def _normalised(parts, t0: float, scale: float, sigma: float) -> np.ndarray:
    """(a, μ, s) of the fit's units (a over the maximum, μ and s in σ from t0) from components [s, W, s]."""
    return np.ravel([(a / scale, (t - t0) / sigma, s / sigma) for t, a, s in parts])


def _ssr_and_gradient(p: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """SSR = Σ r², r = Σ_k a_k exp(−(x − μ_k)²/2s_k²) − y, and its gradient 2 Jᵀr."""
    a, mu, s = p[0::3, None], p[1::3, None], p[2::3, None]
    z = (x[None, :] - mu) / s
    e = np.exp(-0.5 * z * z)
    r = np.sum(a * e, axis=0) - y
    jac = np.stack([e, a * e * z / s, a * e * z * z / s], axis=1).reshape(-1, x.size)
    return float(r @ r), 2.0 * (jac @ r)


def _hessian(p: np.ndarray, x: np.ndarray, y: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """The SSR's Hessian (2 JᵀJ + 2 Σ r ∇²r: with noise the second term matters), by central differences of the
    analytic gradient."""
    columns = []
    for i in range(p.size):
        step = np.zeros_like(p)
        step[i] = h
        columns.append((_ssr_and_gradient(p + step, x, y)[1] - _ssr_and_gradient(p - step, x, y)[1]) / (2.0 * h))
    hessian = np.array(columns)
    return 0.5 * (hessian + hessian.T)


def agreement(system: model.WaveformSystem, times: np.ndarray, echo: np.ndarray, host, device) -> tuple[float, ...]:
    """(SSR device / SSR scipy, q / bound, max |Δp| in fit units) of one waveform's components, each (k, 3) rows
    (time [s], amplitude [W], σ [s]) in time order (the module's docstring)."""
    sigma, scale = model.pulse_sigma_s(system), echo.max()
    x, y = (times - times[0]) / sigma, echo / scale
    p_h, p_d = (_normalised(np.asarray(p, dtype=np.float64), times[0], scale, sigma) for p in (host, device))
    ssr_h, ssr_d = _ssr_and_gradient(p_h, x, y)[0], _ssr_and_gradient(p_d, x, y)[0]
    dp, hessian = p_h - p_d, _hessian(p_d, x, y)
    spacing = _normalised(np.spacing(np.asarray(device, dtype=np.float64)), 0.0, scale, sigma)
    rounding = 0.5 * float(np.abs(np.diag(hessian)) @ (ROUNDING_ULPS * spacing) ** 2)
    bound = 2.0 * max(ssr_h - ssr_d, 0.0) + SSR_SLACK * ssr_h + rounding
    return ssr_d / ssr_h, 0.5 * float(dp @ hessian @ dp) / bound, float(np.max(np.abs(dp)))


def compare(system: model.WaveformSystem, t0: np.ndarray, echo: np.ndarray, device: str) -> dict:
    """Per-set maxima over its waveforms: measures' differences (relative, and in units of the last place of the
    half-power time), waveforms whose peaks differ, SSR ratios, q / bound and |Δp| (the module's docstring)."""
    times, measures, peaks, parts = host_path(system, t0, echo)
    b = process(system, t0, echo, device)
    ulp = np.spacing(np.abs([m.half_power_s for m in measures]))  # one unit in the last place of the echo's times
    out = {"waveforms": len(echo), "components": 0, "peaks_differ": 0, "ssr_ratio_max": 0.0, "q_over_gap_max": 0.0,
           "dp_max": 0.0, "host_fitted": int(np.sum(np.isnan(b.ssr))), "ssr_ratio_min": 1.0,
           "step_cap": int(np.sum(b.status == 1))}
    for name in ("half_power_s", "centroid_s", "peak_s", "fwhm_s", "rms_width_s"):
        host = np.array([getattr(m, name) for m in measures])
        same_nan = np.array_equal(np.isnan(host), np.isnan(b.measures[name]))  # RMS width of a noisy echo: NaN
        out[f"{name}_rel"] = float(np.nanmax(np.abs(b.measures[name] - host) / np.abs(host))) if same_nan else np.inf
        out[f"{name}_ulps"] = float(np.nanmax(np.abs(b.measures[name] - host) / ulp)) if same_nan else np.inf
    for w in range(len(echo)):
        k = len(parts[w])
        out["components"] += k
        found = b.peaks[w][b.peaks[w] >= 0]
        if b.count[w] != len(peaks[w]) or not np.array_equal(found, peaks[w][:len(found)]):
            out["peaks_differ"] += 1
        if np.isnan(b.ssr[w]):
            continue
        device_parts = np.column_stack([b.time_s[w, :k], b.amplitude_w[w, :k], b.sigma_s[w, :k]])
        ratio, q, dp = agreement(system, times[w], echo[w], [(g.time_s, g.amplitude_w, g.sigma_s) for g in parts[w]],
                                 device_parts)
        out["ssr_ratio_max"] = max(out["ssr_ratio_max"], ratio)
        out["ssr_ratio_min"] = min(out["ssr_ratio_min"], ratio)
        out["q_over_gap_max"] = max(out["q_over_gap_max"], q)
        out["dp_max"] = max(out["dp_max"], dp)
    return out


def table(device: str, quick: bool = False) -> str:
    """The comparison as a Markdown table."""
    rows = ["| waveforms | n | components | measures: max rel. difference (half-power, centroid, peak, FWHM, RMS) "
            "| peaks differing | SSR device / scipy: min, max | q / bound, max | max abs Δp (fit units) "
            "| device fits at the step cap |",
            "|---|---|---|---|---|---|---|---|---|"]
    for name, system, t0, echo in waveform_sets(device, quick):
        c = compare(system, t0, echo, device)
        rel = ", ".join(f"{c[f'{m}_rel']:.1e}" for m in ("half_power_s", "centroid_s", "peak_s", "fwhm_s", "rms_width_s"))
        rows.append(f"| {name} | {c['waveforms']} | {c['components']} | {rel} | {c['peaks_differ']} | "
                    f"{c['ssr_ratio_min']:.12f}, {c['ssr_ratio_max']:.12f} | {c['q_over_gap_max']:.2f} | "
                    f"{c['dp_max']:.1e} | {c['step_cap']} |")
    return "\n".join(rows)


def timing(device: str, waveforms: int = 2000, samples: int = 1000, system: model.WaveformSystem | None = None,
           host_waveforms: int = 100, repeats: int = 3) -> dict:
    """Waveforms per second of the host path (measure + decompose, one at a time, over the first ``host_waveforms``)
    and of the device path (:func:`process`, end to end from host arrays to host arrays, best of ``repeats``) on the
    same synthetic chunk (by default GEDI's σ and Δt)."""
    system = system or model.WaveformSystem(pulse_fwhm_s=1.5e-8, sample_interval_s=1e-9)
    _, _, t0, echo = synthetic("timing", system, waveforms, samples, 3)
    process(system, t0[:8], echo[:8], device)  # compile, warm up
    device_s = []
    for _ in range(repeats):
        started = time.perf_counter()
        process(system, t0, echo, device)
        device_s.append(time.perf_counter() - started)
    few = min(waveforms, host_waveforms)
    times = t0[:few, None] + system.sample_interval_s * np.arange(samples)[None, :]
    started = time.perf_counter()
    for w in range(few):
        model.measure(system, times[w], echo[w])
        model.decompose(system, times[w], echo[w])
    host_s = (time.perf_counter() - started) / few
    return {"case": f"σ {model.pulse_sigma_s(system) * 1e9:.2f} ns, Δt {system.sample_interval_s * 1e9:g} ns",
            "device": device, "waveforms": waveforms, "samples": samples, "device_s": min(device_s),
            "device_waveforms_per_s": waveforms / min(device_s), "host_waveforms_per_s": 1.0 / host_s,
            "speedup": host_s * waveforms / min(device_s)}


def ranging_bench(device: str, s) -> list[dict]:
    """`flightsim bench` section ranging: waveforms/s of waveforms.h5's ranging, host vs device, on GEDI-like
    waveforms (1000 samples of 1 ns, σ 6.4 ns) and change1-like ones (32,768 samples of 0.01 ns, σ 3.0 ns)."""
    cuda = not str(device).startswith("cpu")
    gedi = 20000 if cuda else (100 if s.quick else 400)
    change1 = 1000 if cuda else (4 if s.quick else 16)
    return [timing(device, gedi, 1000, host_waveforms=50 if s.quick else 100),
            timing(device, change1, 32768, model.WaveformSystem(), host_waveforms=4 if s.quick else 8)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--time", action="store_true", help="waveforms/s of the host and device paths")
    parser.add_argument("--waveforms", type=int, default=2000)
    parser.add_argument("--samples", type=int, default=1000, help="with --time: 1000 (GEDI's σ and Δt) or more")
    args = parser.parse_args()
    from flightsim.core.warp_runtime import init_warp

    init_warp()
    system = model.WaveformSystem() if args.samples > 4096 else None  # change1's σ and Δt for long waveforms
    print(timing(args.device, args.waveforms, args.samples, system) if args.time else table(args.device, args.quick))


if __name__ == "__main__":
    main()
