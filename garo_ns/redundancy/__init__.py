"""GARO's redundancy measurement as pure torch functions: activity, normals, curvature (with kNN), and
the joint selection. Nothing here knows nerfstudio, gsplat or the model.

May import: `ops` only.
"""
