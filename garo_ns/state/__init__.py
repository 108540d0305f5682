"""The model's state on disk: nerfstudio's checkpoints written and read crash-safely (`checkpoints`) and the
compact half-precision file of a finished model (`storage`).

May import: `engine` (a checkpoint's Gaussians are set up as a run's first ones), `ops`, and the root's
`deformation` and `errors`. Never the plugin's face, `tools` or `bench`.
"""
