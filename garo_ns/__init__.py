"""garo_ns: deformable 3D Gaussian splatting with GARO redundancy pruning, for nerfstudio."""

__version__ = "0.1.0"
