"""The airborne Risley instrument (a 3×3 beam fan through a rotating wedge) on a one-second line over the calibration
field: the plane RMS of both georeferencing models (exact, and the rigid-array nominal one) and the points of each."""
import argparse

import flightsim

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
parser.add_argument("--out", help="also write the run's files to this directory")
args = parser.parse_args()
cfg = flightsim.load_config(instrument="risley", overrides={"flight.duration_s": 1.0, "run.device": args.device})
result = flightsim.simulate(cfg)
if args.out:
    result.write(args.out)
rms = ", ".join(f"{model} {rms * 1e3:.3g} mm" for model, rms in result.stats["rms_m"].items())
points = ", ".join(f"{model} {len(las.points)}" for model, las in result.points.items())
print(f"risley: plane RMS {rms}; points {points}")
