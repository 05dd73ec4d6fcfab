"""`python -m flightsim` runs the command line."""
import sys

from flightsim.cli import main

sys.exit(main())
