"""CPU and GPU photon events for the same seed: the detector alone and a short traced spad run.

    PYTHONPATH=$PWD python3 tests/compare_photons.py      (on a machine with CUDA; results/spad/cpu_vs_gpu.md)
"""
import numpy as np
import flightsim
from flightsim.instrument.photon import PhotonSettings as PhotonConfig
from flightsim.instrument.photon import detect
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.engine.readouts.photons import Photons

s = PhotonConfig(noise_hz=1e6, dead_time_s=2e-8, max_events=16, tdc_bin_s=2.5e-10)
n, t0 = np.full(200000, 1.5), np.full(200000, 1e-6)
a, g = detect(s, n, t0, seed=9, device="cpu"), detect(s, n, t0, seed=9, device="cuda")
print("detector: counts equal", np.array_equal(a.counts, g.counts), "times max diff", np.abs(a.times - g.times).max(),
      "flags equal", np.array_equal(a.signal, g.signal), "photons", a.counts.sum())
runs = {}
for device in ("cpu", "cuda"):
    cfg = flightsim.load_config(instrument="spad", overrides={"flight.duration_s": 0.004, "run.device": device})
    scene = build_scene(cfg)
    sim = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    parts = []
    sim.run(Photons(), parts.append)
    runs[device] = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ("pulse", "pixel", "time_of_flight_s", "signal")}
c, g = runs["cpu"], runs["cuda"]
print("traced: photons", len(c["pulse"]), len(g["pulse"]), "same events", all(np.array_equal(c[k], g[k]) for k in ("pulse", "pixel", "signal")),
      "tof max diff [s]", np.abs(c["time_of_flight_s"] - g["time_of_flight_s"]).max() if len(c["pulse"]) == len(g["pulse"]) else "n/a")
if len(c["pulse"]) == len(g["pulse"]):
    d = np.abs(c["time_of_flight_s"] - g["time_of_flight_s"])
    print("tof differing events", int((d > 0).sum()), "of", len(d))
