"""worldbake's engine: stage contract, graph, store, config, OpenCL, EXR/USD I/O, CLI."""
