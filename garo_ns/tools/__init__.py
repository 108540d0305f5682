"""The command-line tools: training in-process, `garo-eval`, `garo-export`, `garo-camera-path`, `garo-make-scene`
(the built-in scene) and `garo-demo`, and the FPS protocol they time renders with (`fps`).

The top floor with `bench`: may import every room and the plugin's face, never the harness (`bench` imports the
tools: the benchmark trains, scores and times through them). Nothing below imports a tool.
"""
