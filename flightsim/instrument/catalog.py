"""The built-in instrument parts (emitters, deflectors, detectors, the ranging error model), registered by
importing their modules."""
from flightsim.instrument import channels, discrete, fan, fixed, fsm, galvo, pairs, panoramic, photon, ranging  # noqa: F401
from flightsim.instrument import risley, risley_multi, waveform  # noqa: F401
