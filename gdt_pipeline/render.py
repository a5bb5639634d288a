"""A small offscreen renderer for twins: what a plain USD viewer shows, read with plain pxr, drawn with numpy.

usd-core ships no Hydra renderer and the machines have no GPU, so this draws the stage itself, honouring exactly
what viewers honour: prim visibility, world transforms, mesh ``holeIndices``, point ``widths`` (0 = hidden) and
``displayColor`` (constant, uniform or vertex). Facets are drawn as dense area-weighted samples, points as pixels,
with a z-buffer; the camera is orthographic. It reads only USD, so it checks the file, not our arrays.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Usd, UsdGeom

from .types.triangles import triangle_areas, triangle_points


def _world(prim: Usd.Prim, cache: UsdGeom.XformCache, local: np.ndarray) -> np.ndarray:
    m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)  # row-vector convention
    return local @ m[:3, :3] + m[3, :3]


def _colors(prim: Usd.Prim, n_uniform: int, n_vertex: int) -> tuple[np.ndarray, str]:
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    if not pv or pv.Get() is None:
        return np.full((1, 3), 0.5), "constant"
    col = np.asarray(pv.Get(), dtype=np.float64).reshape(-1, 3)
    interp = pv.GetInterpolation()
    if interp in ("uniform", "vertex", "varying") and len(col) in (n_uniform, n_vertex):
        return col, interp
    return col[:1], "constant"


def scene_samples(stage: Usd.Stage, *, samples_per_unit2: float, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray]:
    """World positions and colours of everything visible on the stage: facet samples and points."""
    cache = UsdGeom.XformCache()
    pts_all, col_all = [], []
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.PointBased):
            continue
        if UsdGeom.Imageable(prim).ComputeVisibility() == UsdGeom.Tokens.invisible:
            continue
        local = np.asarray(UsdGeom.PointBased(prim).GetPointsAttr().Get(), dtype=np.float64)
        world = _world(prim, cache, local)
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
            keep = np.ones(len(faces), dtype=bool)
            holes = mesh.GetHoleIndicesAttr().Get()
            if holes:
                keep[np.asarray(holes, dtype=np.int64)] = False
            col, interp = _colors(prim, len(faces), len(world))
            tri = world[faces[keep]]
            area = triangle_areas(tri)
            counts = np.maximum(1, np.round(area * samples_per_unit2)).astype(np.int64)
            idx = np.repeat(np.arange(len(tri)), counts)
            r1, r2 = rng.random(len(idx)), rng.random(len(idx))
            pts_all.append(triangle_points(tri, idx, r1, r2))
            face_ids = np.flatnonzero(keep)[idx]
            if interp == "uniform":
                col_all.append(col[face_ids])
            elif interp in ("vertex", "varying"):
                col_all.append(col[faces[face_ids, 0]])
            else:
                col_all.append(np.repeat(col, len(idx), axis=0))
        else:
            widths = UsdGeom.Points(prim).GetWidthsAttr().Get()
            shown = np.ones(len(world), dtype=bool)
            if widths is not None and len(widths) == len(world):
                shown = np.asarray(widths) > 0
            col, interp = _colors(prim, len(world), len(world))
            pts_all.append(world[shown])
            col_all.append(col[shown] if interp != "constant" else np.repeat(col, int(shown.sum()), axis=0))
    if not pts_all:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(pts_all), np.concatenate(col_all)


class OrthoCamera:
    """An orthographic camera looking along ``direction`` at the bounds of the scene, fitted to the image."""

    def __init__(self, lower: np.ndarray, upper: np.ndarray, direction: np.ndarray, up: np.ndarray,
                 width: int, height: int) -> None:
        d = np.asarray(direction, dtype=np.float64)
        self.forward = d / np.linalg.norm(d)
        right = np.cross(self.forward, up)
        if np.linalg.norm(right) < 1e-9:
            right = np.cross(self.forward, [1.0, 0.0, 0.0])
        self.right = right / np.linalg.norm(right)
        self.up = np.cross(self.right, self.forward)
        corners = np.array([[x, y, z] for x in (lower[0], upper[0]) for y in (lower[1], upper[1])
                            for z in (lower[2], upper[2])])
        u, v = corners @ self.right, corners @ self.up
        self.u0, self.v0 = u.min(), v.min()
        span = max((u.max() - u.min()) / width, (v.max() - v.min()) / height) * 1.05
        self.scale = 1.0 / span if span > 0 else 1.0
        self.width, self.height = width, height
        self.pad_u = (width - (u.max() - u.min()) * self.scale) / 2
        self.pad_v = (height - (v.max() - v.min()) * self.scale) / 2

    def project(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel column, pixel row and depth of world points."""
        col = ((pts @ self.right - self.u0) * self.scale + self.pad_u).astype(np.int64)
        row = (self.height - 1 - ((pts @ self.up - self.v0) * self.scale + self.pad_v)).astype(np.int64)
        return col, row, pts @ self.forward


def render_stage(stage: Usd.Stage, *, width: int = 800, height: int = 600,
                 direction: tuple[float, float, float] = (-1.0, 1.0, -1.2), seed: int = 0,
                 bounds: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, OrthoCamera]:
    """Render the visible content of a stage to an (H,W,3) uint8 image; also return the camera used."""
    up_axis = UsdGeom.GetStageUpAxis(stage)
    up = np.array([0.0, 0.0, 1.0]) if up_axis == UsdGeom.Tokens.z else np.array([0.0, 1.0, 0.0])
    rng = np.random.default_rng(seed)
    probe, _ = scene_samples(stage, samples_per_unit2=1.0, rng=rng)
    if bounds is None:
        if len(probe) == 0:
            return np.full((height, width, 3), 255, dtype=np.uint8), None  # type: ignore[return-value]
        bounds = (probe.min(axis=0), probe.max(axis=0))
    lower, upper = (np.asarray(b, dtype=np.float64) for b in bounds)
    cam = OrthoCamera(lower, upper, np.asarray(direction), up, width, height)
    # enough facet samples for about four per pixel of projected area
    density = 4.0 * cam.scale**2
    pts, col = scene_samples(stage, samples_per_unit2=density, rng=rng)
    img = np.full((height, width, 3), 255, dtype=np.uint8)
    if len(pts) == 0:
        return img, cam
    c, r, depth = cam.project(pts)
    ok = (c >= 0) & (c < width) & (r >= 0) & (r < height)
    c, r, depth, col = c[ok], r[ok], depth[ok], col[ok]
    order = np.argsort(-depth, kind="stable")  # far first, so nearer samples overwrite them
    img[r[order], c[order]] = np.clip(np.round(col[order] * 255), 0, 255).astype(np.uint8)
    return img, cam


def render_file(usd_path: str | Path, png_path: str | Path, **kwargs: object) -> Path:
    """Render a USD file (e.g. a twin's root or a flattened export) to a PNG."""
    import open3d as o3d

    stage = Usd.Stage.Open(str(usd_path))
    img, _ = render_stage(stage, **kwargs)  # type: ignore[arg-type]
    png_path = Path(png_path)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    o3d.io.write_image(str(png_path), o3d.geometry.Image(np.ascontiguousarray(img)))
    return png_path
