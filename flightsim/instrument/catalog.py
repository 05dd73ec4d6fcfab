"""The built-in instrument parts (emitters, deflectors, detectors, the ranging error model), registered by
importing their modules."""
from flightsim.instrument import channels, discrete, fan, fixed, fsm, galvo, pairs, photon, ranging, risley  # noqa: F401
from flightsim.instrument import risley_multi, waveform  # noqa: F401
