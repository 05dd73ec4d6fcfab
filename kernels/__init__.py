"""Device side of flightsim: every Warp kernel and function that runs per pulse or per beam."""
