"""An ATLAS-like photon-counting altimeter in a 500 km orbit over a plane: a 0.05 s pass (500 shots of six beams);
the photons, and the mean height of those the signal finder marks as ground (signal_conf_ph == 4, in ATL03 names)."""
import argparse

import flightsim

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
parser.add_argument("--out", help="also write the run's files to this directory")
args = parser.parse_args()
cfg = flightsim.load_config(instrument="atlas", overrides={"flight.duration_s": 0.05, "run.device": args.device})
result = flightsim.simulate(cfg)
if args.out:
    result.write(args.out)
photons = result.photons
ground = photons["h_ph"][photons["signal_conf_ph"] == 4]
print(f"atlas: {photons.sizes['photon']} photons, {ground.size} on the ground at mean height {float(ground.mean()):.3f} m")
