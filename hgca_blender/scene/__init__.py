"""Blender data from arrays: scans and completion results as meshes and point clouds, their colours, classes and
confidence, the region boxes, and the scene's georeference origin. Imports nothing from the other groups."""
