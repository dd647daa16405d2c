"""A run: the named stages from the inputs to the outputs, the orchestrator that runs them in order, the PIV
cache, the quality and uncertainty assessment, STIV beside PIV, extra sections, and the output staging."""
