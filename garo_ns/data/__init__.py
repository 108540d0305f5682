"""The dataparsers the plugin registers: `garo-dnerf-data` (D-NeRF's layout, checked before training) and
`nerfds-data` (NeRF-DS / HyperNeRF captures and nerfstudio's processed videos, read into one `Capture`).

May import: `render` (a camera's view and the scene's extent), and the root's `compat` and `errors`.
"""
