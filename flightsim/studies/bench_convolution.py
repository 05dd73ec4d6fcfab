"""The waveforms' pulse convolution timed and checked on one chunk: the direct sums (``waveform.convolution =
"direct"``) against overlap-save tile FFTs (``"fft"``, each FFT size N and block_dim asked for), both on the same
impulse trains of the change1 preset (shots at 1 kHz) on the device, each beside the error of its float32 waveforms
against the float64 NumPy convolution of the same trains (max |out − ref| over a row's peak, over the first rows),
the samples it wrote beyond the taps' reach of the touched span (must be 0), and, on CUDA, the GPU time of the
accumulation it follows (emit_rays, pilot and deposit of the same run; in the JSON also the direct convolution of that run).

    python3 -m flightsim.studies.bench_convolution --device cuda [--shots 500] [--fft 8192:256,8192:256:256:0] [--out DIR]

prints a Markdown table; with --out also writes DIR/convolution.json and DIR/convolution.md.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import resolve_device
from flightsim.engine.readouts.convolution import PulseConvolution
from flightsim.engine.readouts.waveforms import Waveforms
from flightsim.studies.bench_common import kernel_times, simulator
from kernels import waveform_fft as kf

CHECKED_ROWS = 16  # rows whose error against the float64 convolution is measured
ACCUMULATION = ("emit_rays", "pilot", "clear_impulses", "start_span", "deposit")  # the kernels before the convolution


def captured_chunk(scene: str, device: str, shots: int) -> dict:
    """The first chunk's impulse trains and spans (device copies), the pulse taps and, on CUDA, the GPU time of the
    run's accumulation kernels [s] of the change1 preset over ``scene`` (flat, slope) with ``shots`` shots."""
    from flightsim.studies.waveform import waveform_config

    shots_set = {"fixed.prf_hz": 1000.0, "flight.duration_s": (shots - 0.5) / 1000.0}
    kept, readout = {}, Waveforms(on_device=True)

    def consume(found):
        if not kept:
            b = readout.buffers
            kept.update(impulses=wp.clone(b.impulses[:found.count]), span=wp.clone(b.span[:found.count]))

    # the trains captured from a run that sums directly (the FFTs zero them as they read them)
    simulator(waveform_config(scene, device, **shots_set, **{"waveform.convolution": "direct"})).run(readout, consume)
    sim = simulator(waveform_config(scene, device, **shots_set))
    kernels = kernel_times(lambda: sim.run(Waveforms(on_device=True), lambda found: None)) if device != "cpu" else {}
    taps, first_lag = sim.instrument.detector.pulse_taps(sim.device)
    accumulate = sum(kernels.get(name, 0.0) for name in ACCUMULATION) if kernels else None
    return {**kept, "taps": taps, "first_lag": first_lag, "shots": shots, "scene": scene,
            "accumulation_s": accumulate, "direct_in_run_s": kernels.get("convolve")}


def seconds_per_launch(launch, device: str, repeats: int) -> float:
    """Mean time of ``launch()`` [s] after one that compiles and warms up (CUDA events on a GPU)."""
    launch()
    wp.synchronize_device(device)
    if device == "cpu":
        started = time.perf_counter()
        for _ in range(repeats):
            launch()
        return (time.perf_counter() - started) / repeats
    start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
    wp.record_event(start)
    for _ in range(repeats):
        launch()
    wp.record_event(end)
    wp.synchronize_event(end)
    return wp.get_event_elapsed_time(start, end) * 1e-3 / repeats


def errors(out: np.ndarray, impulses: np.ndarray, span: np.ndarray, taps: np.ndarray, first_lag: int) -> dict:
    """Max error over a row's peak against the float64 NumPy convolution (first CHECKED_ROWS rows with an echo),
    and the samples written beyond the taps' reach of each row's span (all rows)."""
    worst, rows = 0.0, np.flatnonzero(span[:, 0] <= span[:, 1])
    for r in rows[:CHECKED_ROWS]:
        full = np.convolve(impulses[r], taps)
        lag = np.arange(out.shape[1]) - first_lag
        ref = np.where((lag >= 0) & (lag < len(full)), full[np.clip(lag, 0, len(full) - 1)], 0.0)
        worst = max(worst, float(np.abs(out[r] - ref).max() / ref.max()))
    i = np.arange(out.shape[1])[None, :]
    reach = (i >= span[:, :1] + first_lag) & (i <= span[:, 1:] + first_lag + len(taps) - 1)
    return {"max_error_of_peak": worst, "rows_checked": int(min(len(rows), CHECKED_ROWS)),
            "written_beyond_reach": int(np.count_nonzero(out[~reach]))}


def compare(chunk: dict, device: str, ffts: list[tuple[int, ...]], repeats: int) -> list[dict]:
    """One record per path (direct, then each (N, block_dim[, direct_below]) of ``ffts``): time per chunk, error,
    beside the direct path's output (max difference over the peak)."""
    impulses, span = chunk["impulses"], chunk["span"]
    host = {"impulses": impulses.numpy(), "span": span.numpy()}
    out = wp.empty(impulses.shape, dtype=wp.float32, device=device)
    records, direct = [], None
    for method, *fft_args in [("direct",), *(("fft", *f) for f in ffts)]:
        fft = dict(zip(("fft_least", "block_dim", "direct_below", "floor"), fft_args))
        pulse = PulseConvolution(method, chunk["taps"], chunk["first_lag"], impulses.shape[1], device, **fft)
        work = wp.clone(impulses)  # the FFTs zero the trains they read; their values do not change the work
        wall = seconds_per_launch(lambda: pulse.launch(work, span, out, impulses.shape[0]), device, repeats)
        wp.copy(work, impulses)
        pulse.launch(work, span, out, impulses.shape[0])
        power = out.numpy().copy()
        direct = power if direct is None else direct
        record = {"scene": chunk["scene"], "shots": chunk["shots"], "method": method,
                  "fft_size": getattr(pulse, "n", None), "block_dim": getattr(pulse, "block_dim", None),
                  "direct_below": pulse.direct_below if method == "fft" else None,
                  "kept_bins": getattr(pulse, "keep", None),
                  "seconds": wall, "accumulation_s": chunk["accumulation_s"], "direct_in_run_s": chunk["direct_in_run_s"],
                  "max_difference_from_direct_of_peak": float(np.abs(power - direct).max() / max(direct.max(), 1e-300))}
        records.append({**record, **errors(power, host["impulses"], host["span"], chunk["taps"].numpy(),
                                           chunk["first_lag"])})
    return records


def table(records: list[dict]) -> str:
    """The records as a Markdown table."""
    lines = ["| scene | shots | path | N | block_dim | direct below [samples] | bins kept | time per chunk [ms] "
             "| accumulation [ms] | max error / peak (float64 ref.) | vs direct / peak | written beyond reach |",
             "|---" * 12 + "|"]
    dash = lambda value: "–" if value is None else value  # noqa: E731
    for r in records:
        acc = "–" if r["accumulation_s"] is None else f"{r['accumulation_s'] * 1e3:.3f}"
        lines.append(f"| {r['scene']} | {r['shots']} | {r['method']} | {dash(r['fft_size'])} | {dash(r['block_dim'])} "
                     f"| {dash(r['direct_below'])} | {_kept(r)} | {r['seconds'] * 1e3:.3f} | {acc} "
                     f"| {r['max_error_of_peak']:.2e} "
                     f"| {r['max_difference_from_direct_of_peak']:.2e} | {r['written_beyond_reach']} |")
    return "\n".join(lines)


def _kept(record: dict) -> str:
    """The FFT's kept bins as ±K (bins |k| ≤ K; 'all': none dropped; '–': the direct sums)."""
    keep = record.get("kept_bins")
    if record["method"] != "fft":
        return "–"
    return "all" if keep is None or keep < 0 else f"±{keep}"


def _fft_variant(item: str) -> tuple:
    """'N:block_dim[:direct_below[:floor]]' → (N, block_dim, direct_below, floor) as far as given."""
    values = item.split(":")
    fixed = [int(v) for v in values[:3]]
    if len(fixed) > 1:
        fixed[1] = fixed[1] or None  # block_dim 0: PulseConvolution chooses
    return (*fixed, *(float(v) for v in values[3:4]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m flightsim.studies.bench_convolution",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--shots", type=int, default=None, help="shots per scene (500 on CUDA, 4 on the CPU)")
    parser.add_argument("--fft", default=f"{kf.FFT_SIZE}:0",
                        help="comma-separated N:block_dim[:direct_below[:floor]] of the FFT path (block_dim 0: "
                        "the readout's choice; N a power of "
                        f"two; rows whose span is narrower than direct_below samples summed directly, default "
                        f"{kf.DIRECT_BELOW}; the pulse's spectrum kept above floor of its largest, 0: every bin)")
    parser.add_argument("--scenes", default="slope,flat")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", default=None, help="folder for convolution.json and convolution.md")
    args = parser.parse_args(argv)
    device = resolve_device(args.device)
    wp.init()
    shots = args.shots or (4 if device == "cpu" else 500)
    ffts = [_fft_variant(item) for item in args.fft.split(",") if item]
    records = []
    for scene in args.scenes.split(","):
        records += compare(captured_chunk(scene, device, shots), device, ffts, args.repeats)
    text = table(records)
    print(text)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / "convolution.json").write_text(json.dumps({"device": device, "records": records}, indent=1))
        (Path(args.out) / "convolution.md").write_text(f"Device: {device}\n\n{text}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
