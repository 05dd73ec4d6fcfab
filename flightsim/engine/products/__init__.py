"""Products: what a run to a directory writes from its readout (LAS tiles and their scores, photon files, waveform
files), one module each, registered under the role ``product`` by the name of the readout they write.

A product is made in two steps: ``Product(cfg, scene)`` checks and plans before the output directory is touched
(bad input fails there, leaving nothing behind) and says what the tracer needs (``tracer_options``);
``open(tracer, directory, cfg_text)`` creates its writers. The engine then runs ``readout()`` with the product as
the consumer of every chunk, and ``close(counts)`` finishes the files and gives the product's summary fields
(``abort()`` removes them on failure); ``empty(counts)`` says whether it holds nothing (the run then says why:
:mod:`flightsim.engine.diagnosis`). ``files`` names what it may leave in a run directory.
"""
