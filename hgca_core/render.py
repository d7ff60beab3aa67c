"""A small software renderer for previews: surface samples splatted through a z-buffer, Lambert-shaded.

Used by `hgca demo` (and previews) so a PNG of a completion needs no GPU, display or extra package.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import trimesh


MARK_BIAS = 0.3  # metres a marked point may lie behind the surface drawn at its pixel and still show


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """World -> camera rotation (rows: right, up, forward)."""
    f = target - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    r = r / np.linalg.norm(r)
    return np.stack([r, np.cross(r, f), f])


def render_mesh(mesh: trimesh.Trimesh, path: str | Path, points: np.ndarray | None = None,
                colour_by: np.ndarray | None = None, size: tuple[int, int] = (1200, 800),
                eye: np.ndarray | None = None, target: np.ndarray | None = None, fov_deg: float = 50.0,
                samples: int = 1_500_000, seed: int = 0, marked: np.ndarray | None = None) -> None:
    """Write a PNG of `mesh` (and optional input `points` as yellow dots) seen from `eye` towards `target`.

    `marked` points are drawn red (e.g. the real points a height cut removed from the input), winning over a
    surface up to `MARK_BIAS` in front of them, so points lying on a surface show on it.

    `colour_by` is a per-vertex scalar in metres (e.g. distance to the input): near 0 = observed (grey),
    far = generated (blue), the colouring the Blender material uses too.
    """
    from PIL import Image

    image = mesh_image(mesh, points, colour_by, size, eye, target, fov_deg, samples, seed, marked)
    Image.fromarray(image).save(path)


def mesh_image(mesh: trimesh.Trimesh, points: np.ndarray | None = None, colour_by: np.ndarray | None = None,
               size: tuple[int, int] = (1200, 800), eye: np.ndarray | None = None, target: np.ndarray | None = None,
               fov_deg: float = 50.0, samples: int = 1_500_000, seed: int = 0, marked: np.ndarray | None = None,
               point_rgb: tuple[float, float, float] = (245.0, 200.0, 40.0)) -> np.ndarray:
    """`render_mesh`'s picture as an (h, w, 3) uint8 array, for panels side by side (`gallery`); `point_rgb`
    colours `points` (yellow by default: input points over a completion)."""
    w, h = size
    lo, hi = mesh.bounds if len(mesh.vertices) else (np.zeros(3), np.ones(3))
    target = (lo + hi) / 2 if target is None else np.asarray(target, float)
    span = float(np.linalg.norm(hi - lo))
    eye = target + np.array([-0.55, -0.75, 0.45]) * span if eye is None else np.asarray(eye, float)
    rot = look_at(eye, target)
    focal = 0.5 * w / np.tan(np.radians(fov_deg) / 2)
    depth = np.full(h * w, np.inf)
    image = np.full((h * w, 3), 255.0)

    def splat(pts: np.ndarray, rgb: np.ndarray, radius: int, bias: float = 0.0) -> None:
        cam = (pts - eye) @ rot.T
        front = cam[:, 2] > 0.1
        cam, rgb = cam[front], rgb[front]
        u = (focal * cam[:, 0] / cam[:, 2] + w / 2).astype(np.int64)
        v = (h / 2 - focal * cam[:, 1] / cam[:, 2]).astype(np.int64)
        for du in range(-radius + 1, radius):
            for dv in range(-radius + 1, radius):
                uu, vv = u + du, v + dv
                ok = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
                pix = vv[ok] * w + uu[ok]
                z = cam[ok, 2]
                order = np.argsort(-z)  # far first, so the nearest write wins
                pix, z, col = pix[order], z[order], rgb[ok][order]
                closer = z - bias < depth[pix]
                depth[pix[closer]] = np.minimum(z[closer], depth[pix[closer]])
                image[pix[closer]] = col[closer]

    if len(mesh.faces):
        n = min(samples, max(1000, int(mesh.area / 0.0004)))
        pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
        normals = mesh.face_normals[face]
        light = np.array([0.3, 0.4, 0.85])
        shade = 0.35 + 0.65 * np.abs(normals @ (light / np.linalg.norm(light)))
        base = np.tile([190.0, 190.0, 190.0], (len(pts), 1))
        if colour_by is not None and len(colour_by) == len(mesh.vertices):
            bary = trimesh.triangles.points_to_barycentric(mesh.triangles[face], pts)
            value = np.einsum("ij,ij->i", bary, np.asarray(colour_by, float)[mesh.faces[face]])
            t = np.clip(value / 0.5, 0, 1)[:, None]
            base = (1 - t) * base + t * np.array([70.0, 130.0, 230.0])
        splat(pts, base * shade[:, None], radius=2)
    for cloud, rgb, bias in ((points, list(point_rgb), 0.0), (marked, [220.0, 30.0, 30.0], MARK_BIAS)):
        if cloud is not None and len(cloud):
            p = np.asarray(cloud, float)
            if len(p) > 200_000:
                p = p[np.random.default_rng(seed).choice(len(p), 200_000, replace=False)]
            splat(p, np.tile(rgb, (len(p), 1)), radius=1, bias=bias)
    return image.reshape(h, w, 3).clip(0, 255).astype(np.uint8)


def gallery(panels: Sequence[tuple[str, np.ndarray]], path: str | Path, columns: int = 4, title: str = "") -> None:
    """Write `panels` ((caption, image) pairs of one size) as one PNG, `columns` a row, each captioned."""
    from PIL import Image, ImageDraw, ImageFont

    try:
        font = ImageFont.load_default(size=16)
    except TypeError:           # Pillow < 10.1: the fixed bitmap font
        font = ImageFont.load_default()
    if not panels:
        raise ValueError("gallery: no panels")
    h, w = panels[0][1].shape[:2]
    if any(img.shape[:2] != (h, w) for _, img in panels):
        raise ValueError("gallery: panels differ in size")
    caption = 22
    top = caption if title else 0
    rows = -(-len(panels) // columns)
    sheet = Image.new("RGB", (columns * w, top + rows * (h + caption)), "white")
    draw = ImageDraw.Draw(sheet)
    if title:
        draw.text((6, 2), title, fill=(0, 0, 0), font=font)
    for i, (text, img) in enumerate(panels):
        x, y = (i % columns) * w, top + (i // columns) * (h + caption)
        draw.text((x + 6, y + 2), text, fill=(0, 0, 0), font=font)
        sheet.paste(Image.fromarray(img), (x, y + caption))
    sheet.quantize(colors=256).save(path, optimize=True)   # a preview: a palette halves the file


def render_closeup(mesh: trimesh.Trimesh, eye: np.ndarray, target: np.ndarray, size: tuple[int, int] = (480, 360),
                   fov_deg: float = 45.0, colour_by: np.ndarray | None = None, light: np.ndarray | None = None
                   ) -> np.ndarray:
    """An (h, w, 3) uint8 image of `mesh` by ray casting one ray per pixel (Embree when installed), shaded by the
    hit face's normal (both sides lit alike) under a low light, so ripples of a few millimetres show.

    For close-ups of small parts (a road patch, a facade, a car), where the splatting renderer above blurs the
    shading that shows surface quality; `colour_by` as in `render_mesh`.
    """
    w, h = size
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    rot = look_at(eye, target)
    focal = 0.5 * w / np.tan(np.radians(fov_deg) / 2)
    u, v = np.meshgrid(np.arange(w) + 0.5 - w / 2, h / 2 - (np.arange(h) + 0.5), indexing="xy")
    dirs = np.stack([u.ravel() / focal, v.ravel() / focal, np.ones(u.size)], 1) @ rot
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    image = np.full((h * w, 3), 255.0)
    if len(mesh.faces):
        tri, ray, _ = mesh.ray.intersects_id(np.repeat(eye[None], len(dirs), 0), dirs, multiple_hits=False,
                                               return_locations=True)
        normals = mesh.face_normals[tri]
        ld = np.array([0.35, -0.25, 0.9]) if light is None else np.asarray(light, float)
        ld = ld / np.linalg.norm(ld)
        shade = 0.25 + 0.75 * np.abs(normals @ ld)
        base = np.tile([200.0, 200.0, 200.0], (len(tri), 1))
        if colour_by is not None and len(colour_by) == len(mesh.vertices):
            value = np.asarray(colour_by, float)[mesh.faces[tri]].mean(1)
            t = np.clip(value / 0.5, 0, 1)[:, None]
            base = (1 - t) * base + t * np.array([70.0, 130.0, 230.0])
        image[ray] = base * shade[:, None]
    return image.reshape(h, w, 3).clip(0, 255).astype(np.uint8)
