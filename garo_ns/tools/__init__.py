"""Command-line tools: training in-process, evaluation, export, camera paths, the built-in scene, the demo."""
