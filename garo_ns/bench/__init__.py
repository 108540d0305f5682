"""The measuring harness: the benchmark command, the cross-scene summary and its targets, the paired re-timing and
the frame profile, the training-step profile and the training speed ([docs/benchmarks.md]).

The top floor with `tools`: may import every room, the plugin's face and the tools it drives (training, `garo-eval`,
the FPS protocol of `tools.fps`). Nothing outside the harness imports it.
"""
