"""The command-line tools: training in-process, `garo-eval`, `garo-export`, `garo-camera-path`, `garo-make-scene`
(the built-in scene) and `garo-demo`.

The top floor with `bench`: may import every room and the plugin's face; `garo-demo` times its renders with the
benchmark's FPS protocol (`bench.timing`). Nothing below imports a tool.
"""
