"""`hgca demo` as `make demo` runs it (coarse stage, to keep it quick; `--semantics` as `make demo
DEMO_ARGS=--semantics` adds it): the mesh lies in the example's region, which the bundled poses.json stores as
`Region.as_tuple()` (the --region form, yaw in degrees), and every face carries a class."""
import json
import subprocess
import sys

import numpy as np
import pytest
from plyfile import PlyData

from hgca_core.commands.demo import EXAMPLE_DIR
from hgca_core.geometry.region import Region


@pytest.mark.slow   # minutes on 2 cores: `make test-slow` (CI runs it)
def test_demo_completes_the_bundled_example_in_its_region(tmp_path):
    res = subprocess.run([sys.executable, "-m", "hgca_core.cli", "demo", "--out", str(tmp_path), "--stage", "coarse",
                          "--semantics", "--progress", "none"], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (tmp_path / "completion_s0.png").stat().st_size > 10_000
    ply = PlyData.read(str(tmp_path / "completion_s0.ply"))
    v = ply["vertex"]
    labels = np.asarray(ply["face"]["label"])
    # a street: road, building and more; one class everywhere would be a head that learnt nothing
    assert len(labels) == ply["face"].count and len(np.unique(labels)) >= 3, np.unique(labels)
    region = Region.parse(",".join(map(str, json.loads((EXAMPLE_DIR / "poses.json").read_text())["region"])))
    local = region.to_local(np.c_[v["x"], v["y"], v["z"]].astype(np.float64))
    assert len(local) > 10_000
    # voxel faces reach at most half a 10 cm cell outside the box; a box turned by a wrong yaw pokes out by metres
    assert local.min() > -0.11 and np.all(local.max(0) < region.size + 0.11), (local.min(0), local.max(0))
