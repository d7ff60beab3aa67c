"""Whole drives: tiled completion along a trajectory (`hgca drive`, `hgca_core.drive`).

plan (where tiles go, who owns which place) -> tile (one tile's completion, a pure function) -> runners
(in-process or Ray) -> store (DIR/cache, tiles, drive.json) -> merge (cut at the overlap midlines, weld);
run.drive ties them together. The package is named for what it does, not `drive`, so that `hgca_core.drive`
stays the function."""
