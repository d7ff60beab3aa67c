"""Scan I/O: read point clouds of many formats into one `Scan`, accumulate them with poses, write points
and meshes atomically. Importing this package needs only numpy: laspy, plyfile and trimesh are imported
when a file of their kind is read or written (the Blender add-on may import it where they are absent)."""
from hgca_core.io.formats import FORMATS, format_from_extension, resolve_format
from hgca_core.io.poses import PoseEntry, load_poses, validate_pose
from hgca_core.io.read import read_scan, read_scans
from hgca_core.io.scan import Scan
from hgca_core.io.writers import write_mesh, write_mesh_npz, write_points

__all__ = [
    "FORMATS", "PoseEntry", "Scan", "format_from_extension", "load_poses", "read_scan", "read_scans",
    "resolve_format", "validate_pose", "write_mesh", "write_mesh_npz", "write_points",
]
