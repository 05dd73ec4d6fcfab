"""Readouts: what a detector makes of the beams the tracer traces, chunk by chunk (each one module and one
registration under the role ``readout``; a detector names the readouts it provides)."""
