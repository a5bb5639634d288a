"""Incidence angles for ``sensor_model`` from the twin's own surfaces: a point whose beam crosses a twin facet
(the as-designed CAD, an earlier mesh epoch) within its 3 σ takes that facet's incidence; the others keep the
cloud's PCA normals.

Why: on a low-cost ToF cloud the range noise (6-12 cm at 4 m) is ten times the point spacing, and PCA normals of
20 neighbours then point almost anywhere. 1/cos of such an angle overstated σ along the floor's normal 1.4-1.5×
(median) on the ToF scene family with the true profile; a twice as long σ halves every change's significance. The
known scene's normals are the paper's calibration environment (Sec. 3), and the self-calibration fits its scales
with them too, so the fitted profile is applied the way it was fitted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gdt_pipeline import Composite
from gdt_pipeline.geometry import line_crossings
from gdt_pipeline.sensors import SensorProfile

ACCEPT_SIGMAS = 3.0  # a crossing farther along the beam than this many σ (at its own incidence) is another surface


@dataclass(frozen=True)
class TwinFacets:
    """The twin's visible mesh facets in one Open3D raycasting scene (float32 about ``shift``, so that
    georeferenced coordinates keep their precision) with each geometry's unit facet normals: built once per stage
    call, cast against by every dataset."""

    scene: object
    normals: list[np.ndarray]
    shift: np.ndarray

    @classmethod
    def of(cls, reference: Composite | None, shift: np.ndarray) -> TwinFacets | None:
        """The visible facets of ``reference``'s meshes; None when it holds none."""
        import open3d as o3d

        scene, normals = o3d.t.geometry.RaycastingScene(), []
        for item in reference.items if reference is not None else ():
            ds = item.dataset
            if ds.faces is None or not np.any(item.visible):
                continue
            scene.add_triangles(o3d.core.Tensor((ds.points - shift).astype(np.float32)),
                                o3d.core.Tensor(ds.faces[item.visible].astype(np.uint32)))
            normals.append(ds.facet_normals(unit=True)[item.visible])
        return cls(scene, normals, shift) if normals else None

    def beam_crossings(self, origin: np.ndarray, points: np.ndarray, reach: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every crossing of each point's beam (from ``origin``) with a facet facing the station within ``reach``
        of the point: which point, how far the point lies beyond it along the beam, |cos| of the incidence."""
        beam = points - origin
        unit = beam / np.maximum(np.linalg.norm(beam, axis=1, keepdims=True), 1e-300)
        ray, along, n = line_crossings(self.scene, self.normals, points - self.shift, unit, reach)
        cos = np.einsum("ij,ij->i", n, unit[ray])
        keep = cos < 0  # a beam sees a facet's front only
        return ray[keep], along[keep], -cos[keep]


def surface_cosines(facets: TwinFacets | None, origin: np.ndarray, points: np.ndarray, profile: SensorProfile,
                    units: str) -> tuple[np.ndarray, np.ndarray]:
    """Per point |cos| of the incidence on the twin facet its beam crosses within ``ACCEPT_SIGMAS`` σ (σ at that
    facet's incidence) under which the point is likeliest; NaN where no facet does. Also each point's search
    reach (for a tile's halo)."""
    beam_range = np.linalg.norm(points - origin, axis=1)
    widest, _ = profile.sigmas(beam_range, np.zeros(len(points)), units)  # σ at the incidence floor
    reach = ACCEPT_SIGMAS * widest
    cos = np.full(len(points), np.nan)
    if facets is None or not len(points):
        return cos, reach
    ray, along, found_cos = facets.beam_crossings(origin, points, reach)
    s_range, _ = profile.sigmas(beam_range[ray], found_cos, units)
    z = np.abs(along) / np.maximum(s_range, 1e-300)
    near = z <= ACCEPT_SIGMAS
    # the Gaussian's log density, not z alone: a grazing facet's large σ would otherwise win every tie
    unlikely = 0.5 * z[near] ** 2 + np.log(np.maximum(s_range[near], 1e-300))
    ray, found_cos = ray[near], found_cos[near]
    order = np.lexsort((unlikely, ray))
    first = order[np.r_[True, ray[order][1:] != ray[order][:-1]]] if len(order) else order
    cos[ray[first]] = found_cos[first]
    return cos, reach
