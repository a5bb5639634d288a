"""Data types and the built-in stages' maths: closed forms against numerical integration, geometric queries against
hand-built cases with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate
from scipy.stats import multivariate_normal

from gdt_pipeline import (
    BoxUncertainty,
    ChangeState,
    Composite,
    CompositeItem,
    Dataset,
    GaussianUncertainty,
    RegionOfView,
)
from gdt_pipeline.geometry import ReferenceIndex
from stages.distance import bhattacharyya_gaussian


def _rot(ax: float, ay: float, az: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", [ax, ay, az]).as_matrix()


def _numeric_bc(mu1, cov1, mu2, cov2, n: int = 121) -> float:
    """Bhattacharyya coefficient ∫√(p1 p2) by a dense grid in the frame of the mean covariance.

    The integrand is a smooth, fast-decaying Gaussian-like function, for which the trapezoid rule converges
    exponentially; the grid spans ±9 standard deviations of the narrower of the two along each axis of Σ."""
    cov = (cov1 + cov2) / 2
    w, v = np.linalg.eigh(cov)
    center = (mu1 + mu2) / 2
    half = 9 * np.sqrt(w)
    axes = [np.linspace(-h, h, n) for h in half]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    x = center + g @ v.T
    f = np.sqrt(multivariate_normal(mu1, cov1).pdf(x) * multivariate_normal(mu2, cov2).pdf(x)).reshape(n, n, n)
    val = f
    for ax in axes[::-1]:
        val = integrate.trapezoid(val, ax, axis=-1)
    return float(val)


CASES = [
    # equal isotropic covariances, 2σ apart: second term vanishes
    (np.zeros(3), np.eye(3) * 1e-4, np.array([0.02, 0, 0]), np.eye(3) * 1e-4),
    # strongly anisotropic (flat ToF-like ellipsoid, 10:1) against a small isotropic one, turned
    (np.array([0.1, 0.2, 0.3]), _rot(0.3, -0.2, 1.1) @ np.diag([1e-4, 1e-6, 1e-6]) @ _rot(0.3, -0.2, 1.1).T,
     np.array([0.105, 0.198, 0.301]), np.eye(3) * 4e-6),
    # near-singular: 1000:1 axis ratio
    (np.zeros(3), np.diag([1.0, 1.0, 1e-6]), np.array([0.5, -0.2, 0.001]), np.diag([0.5, 2.0, 2e-6])),
]


@pytest.mark.parametrize("mu1,cov1,mu2,cov2", CASES)
def test_gaussian_bhattacharyya_matches_numerical_integration(mu1, cov1, mu2, cov2) -> None:
    bd = bhattacharyya_gaussian(mu1[None], cov1[None], mu2[None], cov2[None])[0]
    bc_numeric = _numeric_bc(mu1, cov1, mu2, cov2)
    assert np.exp(-bd) == pytest.approx(bc_numeric, rel=1e-6)


def test_gaussian_bhattacharyya_properties() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(500, 3, 3))
    b = rng.normal(size=(500, 3, 3))
    c1 = a @ np.swapaxes(a, 1, 2) + 1e-3 * np.eye(3)
    c2 = b @ np.swapaxes(b, 1, 2) + 1e-3 * np.eye(3)
    m1, m2 = rng.normal(size=(500, 3)), rng.normal(size=(500, 3))
    d12 = bhattacharyya_gaussian(m1, c1, m2, c2)
    np.testing.assert_allclose(d12, bhattacharyya_gaussian(m2, c2, m1, c1), rtol=1e-10)
    assert np.all(d12 >= 0)
    np.testing.assert_allclose(bhattacharyya_gaussian(m1, c1, m1, c1), 0, atol=1e-10)
    # equal covariances: BD = Mahalanobis² / 8
    maha = np.einsum("ni,nij,nj->n", m2 - m1, np.linalg.inv(c1), m2 - m1)
    np.testing.assert_allclose(bhattacharyya_gaussian(m1, c1, m2, c1), maha / 8, rtol=1e-9)


def test_box_covariance_is_the_uniform_second_moment() -> None:
    h = np.array([0.002, 0.005, 0.001])
    box = BoxUncertainty(h[None])
    cov = box.covariance(1)[0]
    for i in range(3):
        var, _ = integrate.quad(lambda x, hh=h[i]: x * x / (2 * hh), -h[i], h[i])
        assert cov[i, i] == pytest.approx(var, rel=1e-12)
    rot = _rot(0.4, 0.1, -0.7)
    turned = BoxUncertainty(h[None], rot[None]).covariance(4)
    assert turned.shape == (4, 3, 3)
    np.testing.assert_allclose(turned[2], rot @ np.diag(h**2 / 3) @ rot.T, rtol=1e-12)
    with pytest.raises(ValueError, match="orthonormal"):
        BoxUncertainty(h[None], np.eye(3)[None] * 2)


def test_dataset_checks_and_immutability() -> None:
    pts = np.random.default_rng(0).normal(size=(10, 3))
    ds = Dataset("scan", "as-is", pts)
    assert ds.kind == "points" and ds.n_elements == 10
    with pytest.raises(ValueError, match="read-only"):
        ds.points[0, 0] = 1.0
    pts[0, 0] = 99.0  # the caller's array is not shared
    assert ds.points[0, 0] != 99.0
    with pytest.raises(ValueError, match="face indices outside"):
        Dataset("m", "as-designed", pts, faces=[[0, 1, 10]])
    with pytest.raises(ValueError, match=r"expected shape \(N, 3\)"):
        Dataset("m", "as-designed", pts[:, :2])
    with pytest.raises(ValueError, match="1 to broadcast"):
        ds.with_uncertainty(GaussianUncertainty(np.tile(np.eye(3), (3, 1, 1))))


def test_a_dataset_rebuilt_shares_its_frozen_arrays_and_copies_writable_ones() -> None:
    """A dataset given its uncertainty keeps the points it had (24 B a point were copied per rebuild); an array
    someone can still write, or a read-only view of one, is copied."""
    pts = np.random.default_rng(1).normal(size=(10, 3))
    ds = Dataset("scan", "as-is", pts)
    cov = np.tile(np.eye(3) * 1e-6, (10, 1, 1))
    given = ds.with_uncertainty(GaussianUncertainty(cov))
    assert given.points is ds.points
    assert given.with_uncertainty(GaussianUncertainty(cov)).uncertainty.cov is not cov  # the caller's is copied
    shared = GaussianUncertainty(given.uncertainty.cov)
    assert shared.cov is given.uncertainty.cov
    view = pts[:, :]
    view.setflags(write=False)
    held = Dataset("view", "as-is", view)
    pts[0, 0] = 42.0  # written through the view's base
    assert held.points[0, 0] != 42.0 and not np.shares_memory(held.points, pts)


def test_transform_rotates_covariances() -> None:
    cov = np.diag([4.0, 1.0, 1.0])
    ds = Dataset("s", "as-is", np.array([[1.0, 0, 0]]), uncertainty=GaussianUncertainty(cov[None]))
    t = np.eye(4)
    t[:3, :3] = _rot(0, 0, np.pi / 2)
    t[:3, 3] = [0, 0, 1]
    moved = ds.transformed(t)
    np.testing.assert_allclose(moved.points, [[0, 1, 1]], atol=1e-12)
    np.testing.assert_allclose(moved.element_covariance()[0], np.diag([1.0, 4.0, 1.0]), atol=1e-12)


def test_region_of_view_box_contains() -> None:
    rov = RegionOfView.box([0, 0, 0], [1, 2, 3])
    pts = np.array([[0.5, 1, 1.5], [1.5, 1, 1], [0.01, 1.99, 2.99], [-0.01, 1, 1]])
    assert rov.contains(pts).tolist() == [True, False, True, False]


def _item(key: str, ds: Dataset, visible=None) -> CompositeItem:
    n = ds.n_elements
    return CompositeItem(key, ds, "E0", np.zeros(n), np.full(n, np.nan), np.zeros(n),
                         np.ones(n, bool) if visible is None else visible)


def test_nearest_finds_points_and_facets() -> None:
    import trimesh

    cube = trimesh.creation.box(extents=(1, 1, 1))
    mesh = Dataset("cube", "as-designed", cube.vertices, faces=cube.faces)
    cloud = Dataset("cloud", "as-is", np.array([[5.0, 0, 0], [5.0, 1.0, 0]]))
    hidden = np.array([True, False])
    comp = Composite((_item("E0_cube", mesh), _item("E0_cloud", cloud, hidden)))
    index = ReferenceIndex(comp)
    q = np.array([[0.7, 0.1, -0.2],   # 0.2 in front of the +x face
                  [5.1, 0.0, 0.0],    # next to the visible cloud point
                  [5.0, 1.05, 0.0],   # next to the hidden point: must match the visible one, 1.05 away
                  [0.0, 0.0, 3.0]])   # 2.5 above the top face
    res = index.nearest(q, max_distance=2.0)
    assert res.item.tolist() == [0, 1, 1, -1]
    np.testing.assert_allclose(res.position[0], [0.5, 0.1, -0.2], atol=1e-6)
    assert res.distance[0] == pytest.approx(0.2, abs=1e-6)
    face_normal = cube.face_normals[res.element[0]]
    np.testing.assert_allclose(face_normal, [1, 0, 0], atol=1e-9)
    assert res.element[1] == 0 and res.distance[1] == pytest.approx(0.1)
    assert res.element[2] == 0 and res.distance[2] == pytest.approx(1.05)  # the hidden point is skipped
    assert np.isnan(res.distance[3]) and res.element[3] == -1


def test_large_coordinates_keep_precision() -> None:
    """Open3D works in float32: the index must work relative to a local origin (UTM ~ 1e6 m)."""
    import trimesh

    offset = np.array([634000.0, 4831000.0, 80.0])
    cube = trimesh.creation.box(extents=(10, 10, 10))
    mesh = Dataset("cube", "as-designed", cube.vertices + offset, faces=cube.faces)
    index = ReferenceIndex(Composite((_item("E0_cube", mesh),)))
    q = offset + np.array([[5.003, 1.0, 2.0]])
    res = index.nearest(q)
    assert res.distance[0] == pytest.approx(0.003, abs=2e-5)


def test_change_state_codes_are_stable() -> None:
    assert [s.value for s in ChangeState] == [0, 1, 2, 3, 4]
    assert [s.name.lower() for s in ChangeState] == ["unchanged", "new", "removed", "outside_rov", "not_comparable"]
