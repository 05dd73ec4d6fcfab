"""The Chang'e-1 waveform altimeter at 200 km over a sloping plane: three shots (4 Hz for half a second), each a full
received waveform; the shot count and each shot's half-power range from result.waveforms (GEDI L1B names)."""
import argparse

import flightsim

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
parser.add_argument("--out", help="also write the run's files to this directory")
args = parser.parse_args()
cfg = flightsim.load_config(instrument="change1", overrides={"fixed.prf_hz": 4.0, "run.device": args.device})
result = flightsim.simulate(cfg)
if args.out:
    result.write(args.out)
ranges = ", ".join(f"{r:.3f}" for r in result.waveforms["range_halfpower_m"].values)
print(f"change1: {result.waveforms.sizes['shot']} shots, half-power range {ranges} m")
