"""The parts of the random scene suite, as watertight trimesh solids with outward normals (metres, base on z = 0 in
their own frame): cabinets, pipes, columns and drums, plates, L-brackets, rails and the floor plate; and their
footprints on the floor (oriented rectangles) with the overlap test the layout uses.

Boxes and extruded profiles keep the few big triangles real CAD has (a floor is two triangles on top)."""

from __future__ import annotations

import numpy as np

CYLINDER_SECTIONS = 32


def box(extents: tuple[float, float, float]):  # -> trimesh.Trimesh
    """A box standing on z = 0, centred on the z axis."""
    import trimesh

    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation((0.0, 0.0, extents[2] / 2))
    return mesh


def cylinder(diameter: float, length: float, *, lying: bool):  # -> trimesh.Trimesh
    """A closed cylinder on the floor: standing (axis z) or lying (axis x, resting on z = 0)."""
    import trimesh

    mesh = trimesh.creation.cylinder(radius=diameter / 2, height=length, sections=CYLINDER_SECTIONS)
    if lying:
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0.0, 1.0, 0.0)))
        mesh.apply_translation((0.0, 0.0, diameter / 2))
    else:
        mesh.apply_translation((0.0, 0.0, length / 2))
    return mesh


def _is_ear(poly: np.ndarray, idx: list[int], k: int) -> bool:
    """Whether vertex ``idx[k]`` of a counter-clockwise polygon is an ear (convex, no other vertex inside)."""
    a, b, c = poly[idx[k - 1]], poly[idx[k]], poly[idx[(k + 1) % len(idx)]]
    if (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) <= 0:
        return False
    others = poly[[i for i in idx if i not in (idx[k - 1], idx[k], idx[(k + 1) % len(idx)])]]
    if not len(others):
        return True
    d = []
    for p, q in ((a, b), (b, c), (c, a)):
        d.append((q[0] - p[0]) * (others[:, 1] - p[1]) - (q[1] - p[1]) * (others[:, 0] - p[0]))
    return not np.any((d[0] >= 0) & (d[1] >= 0) & (d[2] >= 0))


def triangulate_polygon(poly: np.ndarray) -> np.ndarray:
    """Triangles (index triples, counter-clockwise) of a simple counter-clockwise polygon, by ear clipping."""
    # a profile has at most a dozen corners: the quadratic loop over its vertices is negligible
    idx = list(range(len(poly)))
    tris = []
    while len(idx) > 3:
        k = next(k for k in range(len(idx)) if _is_ear(poly, idx, k))
        tris.append([idx[k - 1], idx[k], idx[(k + 1) % len(idx)]])
        idx.pop(k)
    tris.append(idx)
    return np.array(tris, dtype=np.int64)


def prism(profile: np.ndarray, width: float):  # -> trimesh.Trimesh
    """A profile (counter-clockwise polygon in the x-z plane, z ≥ 0) extruded ``width`` along y, centred on y = 0."""
    import trimesh

    n = len(profile)
    caps = triangulate_polygon(profile)
    front = np.column_stack([profile[:, 0], np.full(n, -width / 2), profile[:, 1]])
    back = front + np.array([0.0, width, 0.0])
    verts = np.vstack([front, back])
    # a counter-clockwise (x, z) triangle maps to a normal along -y: the front cap as it is, the back one reversed,
    # and each side quad wound so that its normal is the edge's outward (right-hand) normal
    faces = [caps, caps[:, ::-1] + n]
    i = np.arange(n)
    j = (i + 1) % n
    faces.append(np.column_stack([i, j + n, j]))
    faces.append(np.column_stack([i, i + n, j + n]))
    mesh = trimesh.Trimesh(verts, np.vstack(faces), process=True)
    if mesh.volume < 0:  # whichever way the profile's winding maps to 3D, the normals must point out
        mesh.invert()
    return mesh


def l_bracket(leg_a: float, leg_b: float, thickness: float, width: float):  # -> trimesh.Trimesh
    """An angle bracket: a leg ``leg_a`` on the floor and a leg ``leg_b`` standing up, extruded ``width``."""
    t = thickness
    profile = np.array([[0, 0], [leg_a, 0], [leg_a, t], [t, t], [t, leg_b], [0, leg_b]], dtype=np.float64)
    mesh = prism(profile, width)
    mesh.apply_translation((-leg_a / 2, 0.0, 0.0))
    return mesh


def channel_rail(length: float, width: float, height: float, wall: float):  # -> trimesh.Trimesh
    """A U-channel rail lying open side up (a seat track), ``length`` along x."""
    w, h, t = width, height, wall
    profile = np.array([[0, 0], [w, 0], [w, h], [w - t, h], [w - t, t], [t, t], [t, h], [0, h]], dtype=np.float64)
    mesh = prism(profile, length)
    mesh.apply_translation((-w / 2, 0.0, 0.0))
    import trimesh

    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0.0, 0.0, 1.0)))
    return mesh


def floor_plate(size_x: float, size_y: float, thickness: float = 0.02):  # -> trimesh.Trimesh
    """The base plate: its top face at z = 0, two big triangles."""
    mesh = box((size_x, size_y, thickness))
    mesh.apply_translation((0.0, 0.0, -thickness))
    return mesh


def placed(mesh, yaw: float, xy: tuple[float, float], z: float = 0.0):  # -> trimesh.Trimesh
    """A copy of ``mesh`` turned by ``yaw`` about z and moved to (x, y, z)."""
    import trimesh

    out = mesh.copy()
    t = trimesh.transformations.rotation_matrix(yaw, (0.0, 0.0, 1.0))
    t[:3, 3] = (xy[0], xy[1], z)
    out.apply_transform(t)
    return out


def footprint(mesh) -> np.ndarray:
    """The oriented rectangle (4×2 corners) around a mesh's vertices in x-y, from its minimum-area orientation among
    its own edge directions (exact for the boxes, prisms and cylinders here)."""
    xy = np.asarray(mesh.vertices)[:, :2]
    hull = xy[_convex_hull_2d(xy)]
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.arctan2(edges[:, 1], edges[:, 0])
    best = None
    for a in angles:
        rot = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
        q = hull @ rot.T
        lo, hi = q.min(axis=0), q.max(axis=0)
        area = float(np.prod(hi - lo))
        if best is None or area < best[0] - 1e-12:
            best = (area, rot, lo, hi)
    _, rot, lo, hi = best
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    return corners @ rot


def _convex_hull_2d(xy: np.ndarray) -> np.ndarray:
    """Indices of the convex hull of 2D points, counter-clockwise."""
    from scipy.spatial import ConvexHull

    return ConvexHull(xy).vertices


def rectangles_overlap(a: np.ndarray, b: np.ndarray, clearance: float = 0.0) -> bool:
    """Whether two oriented rectangles (4×2 corners) come closer than ``clearance`` (separating-axis test)."""
    for rect in (a, b):
        e = np.array([rect[1] - rect[0], rect[2] - rect[1]])
        for axis in e / np.linalg.norm(e, axis=1, keepdims=True):
            pa, pb = a @ axis, b @ axis
            if pa.max() + clearance <= pb.min() or pb.max() + clearance <= pa.min():
                return False
    return True
