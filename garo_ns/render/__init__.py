"""Rendering: the camera view, gsplat's kernels or the pure-torch reference, and the frame path that
renders a finished model fast (caches, static split, precision, CUDA graphs)."""
