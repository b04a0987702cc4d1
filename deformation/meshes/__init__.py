"""Meshes: triangle surfaces, tetrahedral meshes of the body, isosurfaces of volumes.

* :mod:`~deformation.meshes.mesh` — triangle surface meshes in world millimetres;
* :mod:`~deformation.meshes.tetmesh` — tetrahedral meshes of a mask, rasterisation, point location;
* :mod:`~deformation.meshes.isosurface` — isosurfaces of volumes (VTK).
"""
