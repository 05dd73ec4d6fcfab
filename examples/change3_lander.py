"""The Chang'e-3 imager (16 channels through a two-mirror galvo, with its ranging chain) hovering 100 m over a plane
for one 0.1 s frame: the points and the exact model's plane RMS."""
import argparse

import flightsim

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
parser.add_argument("--out", help="also write the run's files to this directory")
args = parser.parse_args()
cfg = flightsim.load_config(instrument="change3", overrides={"run.device": args.device})
result = flightsim.simulate(cfg)
if args.out:
    result.write(args.out)
print(f"change3: {len(result.points['exact'].points)} points, exact plane RMS "
      f"{result.stats['rms_m']['exact'] * 1e3:.1f} mm")
