"""Rendering: the camera view, gsplat's kernels or the pure-torch reference, and the frame path that renders a
finished model fast (the time table, the static split and its classification, caches, CUDA graphs, the lean
kernels), with the render switches that choose among them.

May import: `ops` and the root's `deformation`. Never the engine, compaction, the state on disk or the face.
"""
