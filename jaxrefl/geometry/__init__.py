"""Rays and geometry: Embree ray casting, meshes, cameras and rigs, the per-(point, light)
observation geometry, form factors."""
