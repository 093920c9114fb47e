"""Mapping: the two maps built in parallel from the posed RGB-D stream.

``tsdf`` fuses depth and colour into a truncated signed distance volume and a mesh (the geometry
half of GSFixer's condition); ``splat`` holds the 3D Gaussian map, its renderers and its online
optimisation (what users inspect and what repairs are distilled into).
"""
