"""`python -m flightsim` runs the command line."""
import sys

from flightsim.entry import main

sys.exit(main())
