"""The mesh step of a completion: cells or a decoded field in, the mesh that ships out.

- `voxel_mesh`: the coarse stage's cells as cubes (`voxel_mesh`, also every voxel row of `hgca eval`) or, for
  `--stage preview`, as a smooth surface (`smooth_cells_mesh`).
- `field`: the fine stage's unsigned distance decoded on a 5 cm grid around the 10 cm cells.
- `fine`: that field's zero level as one open surface (`udf_mesh`), built from `udf_surface` (extraction),
  `mesh_clean` (fragments, orientation, pinholes, normals) and `fairing` (the ground between the scan rings),
  whose numpy steps run in threads (`parallel`).
- `decimation`: the triangle limit (`--max-faces`).
- `finish`: each vertex's distance to the input, normals and the observed / generated face split.
"""
