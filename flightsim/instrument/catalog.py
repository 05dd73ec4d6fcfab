"""The built-in instrument parts (emitters, deflectors, detectors, the ranging error model), registered by
importing their modules."""
from flightsim.instrument import channels, discrete, fan, fixed, fsm, galvo, panoramic, photon, ranging, risley, waveform  # noqa: F401
