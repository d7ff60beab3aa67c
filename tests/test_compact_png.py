"""scripts/compact_png.py: renderings rewritten as palette PNGs look the same, are smaller, keep transparency,
and files that would not gain are left untouched."""
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "compact_png.py"


def _shaded(h: int = 240, w: int = 320) -> np.ndarray:
    """A blue-grey shaded surface with noise, like a mesh rendering: many RGB values, few distinct hues."""
    rng = np.random.default_rng(0)
    shade = np.linspace(0.4, 1.0, w)[None, :] * np.linspace(0.7, 1.0, h)[:, None]
    img = np.stack([60 * shade, 110 * shade, 200 * shade], -1) + rng.normal(0, 3, (h, w, 3))
    img[:40] = 255   # white sky
    return np.clip(img, 0, 255).astype(np.uint8)


def test_a_rendering_shrinks_and_looks_the_same(tmp_path):
    rgb = _shaded()
    png = tmp_path / "r.png"
    Image.fromarray(rgb).save(png)
    before = png.stat().st_size
    res = subprocess.run([sys.executable, str(SCRIPT), str(png)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    with Image.open(png) as im:
        assert im.mode == "P"
        back = np.asarray(im.convert("RGB")).astype(int)
    assert png.stat().st_size < before / 2
    assert np.abs(back - rgb).mean() < 3 and np.percentile(np.abs(back - rgb), 99) < 16
    again = subprocess.run([sys.executable, str(SCRIPT), str(png)], capture_output=True, text=True)
    assert again.returncode == 0 and f"{png.stat().st_size:,} -> {png.stat().st_size:,}" in again.stdout


def test_transparency_is_kept_and_a_missing_file_is_an_error(tmp_path):
    rgba = np.dstack([_shaded(), np.full(_shaded().shape[:2], 255, np.uint8)])
    rgba[:40, :, 3] = 0
    png = tmp_path / "a.png"
    Image.fromarray(rgba).save(png)
    assert subprocess.run([sys.executable, str(SCRIPT), str(png)], capture_output=True).returncode == 0
    with Image.open(png) as im:
        alpha = np.asarray(im.convert("RGBA"))[..., 3]
    assert (alpha[:40] == 0).all() and (alpha[40:] == 255).all()
    res = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "none.png")], capture_output=True, text=True)
    assert res.returncode == 2 and "no such file" in res.stderr
