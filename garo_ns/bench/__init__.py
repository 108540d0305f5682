"""Benchmarking: the benchmark command, the cross-scene summary, the FPS protocol and the frame profile."""
