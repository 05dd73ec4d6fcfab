"""The device fit's time on a run's own waveforms (results/profile-experiments.md 98).

``python3 -m flightsim.studies.fit_timing RUN/waveforms.h5 --device cuda:0 [--beam BEAM0000] [--shots N]
[--fit-chunk S]``: :func:`flightsim.instrument.waveform_batch.process` over the beam's first ``N`` waveforms (their
window starts and the run's pulse and sampling, noise-free), its wall best of three after a first call that compiles,
then on a GPU each kernel's GPU time over one more call with the rounds launched from the host (Warp's CUDA activity
timing does not see inside a graph). ``--fit-chunk`` sets ``kernels.waveform_fit.FIT_CHUNK`` before any kernel is
built; ``--save OUT.npz`` keeps the fitted components, to hold two settings' fits side by side.
"""
from __future__ import annotations

import argparse
import time
import tomllib

import h5py
import numpy as np


def load(path: str, beam: str, shots: int | None):
    """(WaveformSystem, t0 (W,) [s], echo (W, N) [W]) of ``beam``'s first ``shots`` waveforms in a waveforms.h5."""
    from flightsim.instrument import waveform_model as model

    with h5py.File(path, "r") as f:
        cfg = tomllib.loads(f.attrs["config_toml"])["waveform"]
        g = f[beam]
        count = g["rx_sample_count"][:shots]
        samples = int(count[0])
        if not (count == samples).all():
            raise SystemExit(f"{path}: {beam}'s waveforms are not all {samples} samples long")
        echo = g["rxwaveform"][:len(count) * samples].reshape(len(count), samples)
        t0 = g["rx_window_start_s"][:len(count)].astype(np.float64)
    system = model.WaveformSystem(pulse_fwhm_s=cfg["pulse_fwhm_s"], sample_interval_s=cfg["sample_interval_s"])
    return system, t0, echo


def kernel_times(run) -> dict[str, tuple[int, float]]:
    """Launches and GPU time [ms] of each kernel over one ``run()``, its rounds launched from the host."""
    import warp as wp

    supported = wp.is_conditional_graph_supported
    wp.is_conditional_graph_supported = lambda: False
    try:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        run()
        results = wp.timing_end()
    finally:
        wp.is_conditional_graph_supported = supported
    times: dict[str, tuple[int, float]] = {}
    for r in results:
        n, t = times.get(r.name, (0, 0.0))
        times[r.name] = (n + 1, t + r.elapsed)
    return times


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("waveforms_h5")
    p.add_argument("--device", default="cpu")
    p.add_argument("--beam", default="BEAM0000")
    p.add_argument("--shots", type=int, default=None)
    p.add_argument("--fit-chunk", type=int, default=None)
    p.add_argument("--save", default=None)
    a = p.parse_args(argv)
    if a.fit_chunk is not None:
        from kernels import waveform_fit

        waveform_fit.FIT_CHUNK = a.fit_chunk
    import warp as wp

    from flightsim.instrument.waveform_batch import process
    from kernels.waveform_fit import FIT_CHUNK

    system, t0, echo = load(a.waveforms_h5, a.beam, a.shots)
    run = lambda: process(system, t0, echo, a.device)  # noqa: E731
    batch = run()
    walls = []
    for _ in range(3):
        wp.synchronize()
        start = time.perf_counter()
        run()
        walls.append(time.perf_counter() - start)
    print(f"{len(t0)} waveforms of {echo.shape[1]} samples, FIT_CHUNK {FIT_CHUNK}, on {a.device}: process "
          f"{min(walls):.4f} s (best of {', '.join(f'{w:.4f}' for w in walls)}); Gaussians per waveform "
          f"{np.bincount(batch.count).tolist()}, most steps {int(batch.steps.max())}")
    if wp.get_device(a.device).is_cuda:
        for name, (n, ms) in sorted(kernel_times(run).items(), key=lambda kv: -kv[1][1])[:6]:
            print(f"  {name.split()[-1]}: {n} launches, {ms:.2f} ms")
    if a.save:
        np.savez(a.save, time_s=batch.time_s, amplitude_w=batch.amplitude_w, sigma_s=batch.sigma_s,
                 count=batch.count, steps=batch.steps, ssr=batch.ssr)


if __name__ == "__main__":
    main()
