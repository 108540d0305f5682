"""The lowest room: operations any other room may use, knowing nothing of the model, nerfstudio or gsplat.

* `dense`: the deformation MLP's layers as tensor-core products;
* `quaternions`: quaternions as rotation matrices;
* `collector`: Python's garbage collector while training and around a CUDA graph's capture.
* `alpha_reach`: the box where a splat's alpha can reach the rasterizer's 1/255 skip threshold (its tiles).

May import: torch and the standard library only.
"""
