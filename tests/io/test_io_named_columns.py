"""Text tables read by the names in their header, wherever the columns stand and however the header is marked.

Each table here used to be read by position (or lost a row to a byte-order mark), giving points that looked
fine and were wrong; the refusals of the same class are cases in tests/hostile/reads.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from hgca_core.io import read_scan

XYZ = np.array([[500_000.25, 5_000_000.5, 101.75], [500_003.0, 5_000_004.0, 102.5], [500_001.5, 5_000_002.5, 99.0]])
ID = np.array([7.0, 8.0, 9.0])


def table(columns: list[np.ndarray], sep: str = ",") -> str:
    return "".join(sep.join(f"{v:.3f}" for v in row) + "\n" for row in np.column_stack(columns))


CASES = {
    # file name: (text, the attribute column it also has, or None)
    "bom_zyx.csv": ("\ufeffz,y,x\n" + table([XYZ[:, 2], XYZ[:, 1], XYZ[:, 0]]), None),
    "en.csv": ("id,easting,northing,elevation\n" + table([ID, XYZ[:, 0], XYZ[:, 1], XYZ[:, 2]]), "id"),
    "en_caps.csv": ("ID;Northing;Easting;Height\n" + table([ID, XYZ[:, 1], XYZ[:, 0], XYZ[:, 2]], ";"), "ID"),
    "units.csv": ("Z [m],X [m],Y [m],id\n" + table([XYZ[:, 2], XYZ[:, 0], XYZ[:, 1], ID]), "id"),
    "cloudcompare.txt": ("//Y,X,Z,id\n" + table([XYZ[:, 1], XYZ[:, 0], XYZ[:, 2], ID]), "id"),
    "comment_header.xyz": ("# exported\n# z x y id\n" + table([XYZ[:, 2], XYZ[:, 0], XYZ[:, 1], ID], " "), "id"),
    "quoted.csv": ("".join(",".join(f'"{v:.3f}"' for v in row) + "\n" for row in XYZ), None),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_columns_are_read_by_name(tmp_path, name):
    text, attribute = CASES[name]
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    scan = read_scan(path)
    np.testing.assert_array_equal(scan.points, XYZ)
    if attribute is not None:
        np.testing.assert_array_equal(scan.attributes[attribute], ID)


def test_byte_order_mark_does_not_eat_the_first_row(tmp_path):
    path = tmp_path / "bom.csv"
    path.write_bytes(("\ufeff" + table([XYZ[:, 0], XYZ[:, 1], XYZ[:, 2]])).encode("utf-8"))
    np.testing.assert_array_equal(read_scan(path).points, XYZ)

