"""The batch command line's --region text is read by the add-on itself (it cannot import the core: the extension
ships alone and runs in Blender's Python), so its parser is held to the core's `Region.parse`: the same texts
accepted, the same numbers read, the same texts refused."""
from __future__ import annotations

import numpy as np

from bl_helpers import addon_module, core_arrays

TEXTS = ["1,2,3,4,5,6", "1.5,-2,3e2,38.4,38.4,8,30", "0,0,0,1,1,1,-90", "1,2,3,4,5", "1,2,3,4,5,6,7,8",
         "a,b,c,d,e,f", "1,2,3,0,5,6", "1,2,3,4,-5,6", "1,2,nan,4,5,6", "1,2,3,4,5,inf", "1,2,3,4,5,6,nan", ""]


def test_the_addon_reads_a_region_text_as_the_core_does(addon) -> None:
    region = addon_module("scene.region")
    core = core_arrays(
        "from hgca_core.errors import InputError\nfrom hgca_core.geometry.region import Region\n"
        f"rows, ok = [], []\nfor t in {TEXTS!r}:\n"
        "    try:\n        rows.append(Region.parse(t).as_tuple()); ok.append(True)\n"
        "    except InputError:\n        rows.append((np.nan,) * 7); ok.append(False)\n",
        rows="rows", ok="ok")
    mine, accepted = [], []
    for text in TEXTS:
        try:
            mine.append(region.parse_region(text))
            accepted.append(True)
        except region.RegionError:
            mine.append((np.nan,) * 7)
            accepted.append(False)
    assert accepted == core["ok"].tolist(), list(zip(TEXTS, accepted, core["ok"].tolist()))
    assert sum(accepted) == 3
    got, want = np.array(mine)[accepted], core["rows"][accepted]
    assert np.array_equal(got[:, :6], want[:, :6])
    # the core keeps the yaw in radians: degrees come back within a rounding of the text's
    np.testing.assert_allclose(got[:, 6], want[:, 6], rtol=0, atol=1e-12)
