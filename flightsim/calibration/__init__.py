"""Calibration of a spaceborne single-photon altimeter's pointing and ranging with ground corner
cubes (CCRs), after ``seeds/corner-cube-single-photon-calibration-patent.txt``: the reduced
geolocation model of its eq. (1) (:mod:`.geolocation`), the patent's six steps and a generic
maximum-likelihood estimator (:mod:`.ccr`), and synthetic passes to test them (:mod:`.synthetic`).
Plain float64 NumPy/SciPy on arrays in a local east-north-up frame [m].
"""
from flightsim.calibration.ccr import PatentCalibration, calibrate_patent
from flightsim.calibration.ccr_field import CcrField, FieldDesign, design_field
from flightsim.calibration.ccr_likelihood import LeastSquaresCalibration, calibrate_least_squares
from flightsim.calibration.ccr_lines import common_tangents
from flightsim.calibration.ccr_tracks import Identification, identify_ccr_tracks
from flightsim.calibration.geolocation import (ARCSEC, Bias, Track, geolocate, ground_shift_m, measured_range,
                                               theoretical_radius)
from flightsim.calibration.synthetic import Altimeter, SyntheticPass, simulate_pass

__all__ = ["ARCSEC", "Altimeter", "Bias", "CcrField", "FieldDesign", "Identification", "LeastSquaresCalibration",
           "PatentCalibration", "SyntheticPass", "Track", "calibrate_least_squares", "calibrate_patent",
           "common_tangents", "design_field", "geolocate", "ground_shift_m", "identify_ccr_tracks",
           "measured_range", "simulate_pass", "theoretical_radius"]
