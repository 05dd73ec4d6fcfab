"""The SPAD imager (a 32×32 fan swept by a fast steering mirror, photon counting) hovering 100 m over the sandbox,
for 2 ms of its 0.86 s frame: the photons and the share of them that are signal (echoes, not noise)."""
import argparse

import flightsim

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
parser.add_argument("--out", help="also write the run's files to this directory")
args = parser.parse_args()
cfg = flightsim.load_config(instrument="spad", overrides={"flight.duration_s": 0.002, "run.device": args.device})
result = flightsim.simulate(cfg)
if args.out:
    result.write(args.out)
photons = result.photons
signal = float((photons["truth_kind"] > 0).mean())
print(f"spad: {photons.sizes['photon']} photons, {signal:.1%} signal")
