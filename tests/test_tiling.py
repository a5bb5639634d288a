"""3-D tiles: the grid puts every element in exactly one core, box queries find what a scan would, crops and merges
keep every element and candidate, and the runner's chain runs are cut where they must be."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gdt_pipeline import (
    BoxUncertainty,
    Correspondences,
    Dataset,
    GaussianUncertainty,
    GdtError,
    MixtureUncertainty,
)
from gdt_pipeline.plugins import TileBounds
from gdt_pipeline.runner.plan import StagePlan
from gdt_pipeline.runner.stage_call import element_ordered
from gdt_pipeline.runner.tiled import chain_runs
from gdt_pipeline.tiling import (
    CellIndex,
    ElementOrder,
    grid_for,
    members_of,
    merge_correspondences,
    size_for_budget,
    take_candidates,
)
from gdt_pipeline.types import MappedRows, concat_uncertainty


def _cloud(rng: np.random.Generator, n: int) -> np.ndarray:
    pts = rng.uniform(-1.0, 2.0, (n, 3))
    pts[:50] = np.round(pts[:50] / 0.25) * 0.25  # some exactly on tile faces
    return pts


def test_every_element_is_in_exactly_one_core() -> None:
    rng = np.random.default_rng(1)
    clouds = [_cloud(rng, 5000), _cloud(rng, 300)]
    grid = grid_for(clouds, 0.25)
    members = members_of([CellIndex(grid, c) for c in clouds])
    for d, cloud in enumerate(clouds):
        ids = np.concatenate([m[d] for m in members.values()])
        assert np.array_equal(np.sort(ids), np.arange(len(cloud)))
        for tile, m in members.items():
            lo, hi = grid.bounds(tile)
            inside = cloud[m[d]]
            # lower faces closed, upper faces open, except the grid's last tile along each axis
            assert np.all(inside >= lo - 1e-12) and np.all(inside <= hi + 1e-12)


def test_cell_index_finds_what_a_scan_finds() -> None:
    rng = np.random.default_rng(2)
    cloud = _cloud(rng, 4000)
    grid = grid_for([cloud], 0.4)
    index = CellIndex(grid, cloud)
    for _ in range(20):
        lo = rng.uniform(-1.5, 2.0, 3)
        hi = lo + rng.uniform(0.0, 1.5, 3)
        brute = np.flatnonzero(np.all((cloud >= lo) & (cloud <= hi), axis=1))
        assert np.array_equal(index.query(lo, hi), brute)


def test_core_members_are_views_of_the_cell_index() -> None:
    rng = np.random.default_rng(5)
    clouds = [_cloud(rng, 3000), rng.uniform(1.6, 2.0, (40, 3)), np.zeros((0, 3))]
    grid = grid_for(clouds, 0.5)
    indexes = [CellIndex(grid, c) for c in clouds]
    members = members_of(indexes)
    cells = [grid.cell(c) for c in clouds]
    occupied = np.unique(np.concatenate(cells))
    assert list(members) == occupied.tolist()
    for tile, per in members.items():
        for d, ids in enumerate(per):
            # what an argsort and a sort of each core gave before: the ascending indices of the tile's elements
            assert np.array_equal(ids, np.flatnonzero(cells[d] == tile))
            assert ids.base is indexes[d].order or (len(ids) == 0 and ids.base is not None)
            assert not ids.flags.writeable
    assert all(len(per[2]) == 0 for per in members.values())  # a dataset with no points is empty in every tile
    assert sum(len(per[1]) for per in members.values()) == 40
    assert not hasattr(indexes[0], "sorted_cells")  # 4 B a position that the table of occupied cells replaces
    assert len(indexes[0].occupied) == len(np.unique(cells[0])) < len(clouds[0])
    assert len(indexes[2].query(np.full(3, -9.0), np.full(3, 9.0))) == 0


def test_budget_size_holds_the_budget() -> None:
    rng = np.random.default_rng(3)
    cloud = _cloud(rng, 20000)
    size = size_for_budget([cloud], 2000)
    grid = grid_for([cloud], size)
    assert np.bincount(grid.cell(cloud)).max() <= 2000
    assert np.bincount(grid_for([cloud], 2 * size).cell(cloud)).max() > 2000  # the largest size that fits


def test_a_lost_or_doubled_element_is_an_error() -> None:
    ok = ElementOrder.check("scan", [np.array([0, 2]), np.array([1, 3])], 4)
    assert np.array_equal(ok.position, [0, 2, 1, 3])
    with pytest.raises(GdtError, match="1 elements in no tile's core and 0 in more than one"):
        ElementOrder.check("scan", [np.array([0, 2]), np.array([1])], 4)
    with pytest.raises(GdtError, match="0 elements in no tile's core and 1 in more than one"):
        ElementOrder.check("scan", [np.array([0, 1, 2]), np.array([2, 3])], 4)


def _cov(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, 3, 3))
    return a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(3)


def test_uncertainty_parts_concatenate_row_for_row() -> None:
    rng = np.random.default_rng(4)
    g = [GaussianUncertainty(_cov(rng, 3)), GaussianUncertainty(_cov(rng, 2))]
    assert np.array_equal(concat_uncertainty(g, [3, 2]).cov, np.concatenate([g[0].cov, g[1].cov]))
    shared = GaussianUncertainty.isotropic(0.01)
    assert concat_uncertainty([shared, GaussianUncertainty.isotropic(0.01)], [4, 5]) is shared
    mixed = concat_uncertainty([shared, g[1]], [2, 2])
    assert np.array_equal(mixed.cov, np.concatenate([np.repeat(shared.cov, 2, axis=0), g[1].cov]))
    boxes = concat_uncertainty([BoxUncertainty(np.full((1, 3), 0.002)), BoxUncertainty(np.full((2, 3), 0.001))], [2, 2])
    assert np.array_equal(boxes.half_widths[:, 0], [0.002, 0.002, 0.001, 0.001]) and boxes.rotation is None


def test_mixtures_of_different_sizes_pad_with_weightless_components() -> None:
    one = MixtureUncertainty(np.ones((2, 1)), np.zeros((2, 1, 3)), np.broadcast_to(np.eye(3), (2, 1, 3, 3)))
    two = MixtureUncertainty(np.full((1, 2), 0.5), np.ones((1, 2, 3)), np.broadcast_to(2 * np.eye(3), (1, 2, 3, 3)))
    both = concat_uncertainty([one, two], [2, 1])
    assert both.weights.shape == (3, 2)
    assert np.array_equal(both.weights, [[1, 0], [1, 0], [0.5, 0.5]])
    # the padding changes no mixture: same covariance, row by row
    assert np.allclose(both.covariance(3), np.concatenate([one.covariance(2), two.covariance(1)]))


def test_candidates_merge_into_element_order_with_their_mixture_rows() -> None:
    rng = np.random.default_rng(5)
    n = 40
    element = np.sort(rng.integers(0, n, 90))
    mix = MixtureUncertainty(np.ones((90, 1)), np.zeros((90, 1, 3)), np.broadcast_to(np.eye(3), (90, 1, 3, 3)) *
                             rng.uniform(1, 2, (90, 1, 1, 1)))
    whole = Correspondences(0, rng.integers(0, 2, 90), rng.integers(0, 500, 90), rng.normal(size=(90, 3)),
                            rng.uniform(size=90), "test", element=element, n_elements=n, ref_uncertainty=mix,
                            ref_row=np.where(rng.uniform(size=90) < 0.7, np.arange(90), -1))
    # two "tiles": even and odd elements, each keeping its own candidates, numbered as the whole
    same = [lambda e: e, lambda e: e]
    parts = [take_candidates(whole, whole.element % 2 == k, lambda e: e, same, n) for k in (0, 1)]
    merged, where = merge_correspondences(parts, n, 0)
    assert np.array_equal(merged.element, whole.element)
    assert np.array_equal(merged.ref_element, whole.ref_element)
    assert np.array_equal(merged.position, whole.position)
    used = merged.ref_row >= 0
    assert np.array_equal(used, whole.ref_row >= 0)
    assert np.array_equal(merged.ref_uncertainty.covs[merged.ref_row[used]], mix.covs[whole.ref_row[used]])
    for k, part in enumerate(parts):  # each tile's candidate lands where the whole has it
        assert np.array_equal(np.flatnonzero(whole.element % 2 == k), np.sort(where[k]))
        assert np.array_equal(merged.element[where[k]], part.element)



@pytest.mark.parametrize("query_model", ["gaussian", "student", "box"])
def test_a_releasing_merge_places_every_candidate_as_concatenating_and_sorting_does(query_model: str) -> None:
    rng = np.random.default_rng(17)
    n, m = 60, 150
    sigma = rng.uniform(0.001, 0.01, m)
    query_u = {"gaussian": GaussianUncertainty.isotropic(sigma), "student": GaussianUncertainty.isotropic(sigma, 3.0),
               "box": BoxUncertainty(np.repeat(sigma[:, None], 3, axis=1))}[query_model]
    mix = MixtureUncertainty(np.ones((m, 1)), np.zeros((m, 1, 3)), np.broadcast_to(np.eye(3), (m, 1, 3, 3)) *
                             rng.uniform(1, 2, (m, 1, 1, 1)))
    whole = element_ordered(Correspondences(
        0, rng.integers(0, 3, m), rng.integers(0, 500, m), rng.normal(size=(m, 3)), rng.uniform(size=m), "test",
        element=rng.integers(0, n, m), n_elements=n, query_position=rng.normal(size=(m, 3)),
        query_uncertainty=query_u, ref_uncertainty=mix, ref_row=np.where(rng.uniform(size=m) < 0.5, np.arange(m), -1)))
    same = [lambda e: e] * 3
    tile_of = rng.integers(0, 3, n)  # three "tiles" of random elements
    parts = [take_candidates(whole, tile_of[whole.element] == k, lambda e: e, same, n) for k in range(3)]
    kept, kept_where = merge_correspondences(list(parts), n, 0)
    handed = list(parts)
    merged, where = merge_correspondences(handed, n, 0, release=True)
    assert handed == []  # the merge let go of the tiles' candidates
    for a, b in zip(where, kept_where, strict=True):
        assert np.array_equal(a, b)
    for name in ("element", "ref_item", "ref_element", "position", "distance", "query_position"):
        assert np.array_equal(getattr(merged, name), getattr(whole, name)), name
    assert np.array_equal(merged.ref_row, kept.ref_row)  # rows of the joined mixtures, numbered as the tiles' join
    assert type(merged.query_uncertainty) is type(query_u)
    assert np.array_equal(merged.query_uncertainty.covariance(m), whole.query_uncertainty.covariance(m))
    assert getattr(merged.query_uncertainty, "dof", None) == getattr(query_u, "dof", None)
    used = merged.ref_row >= 0
    assert np.array_equal(merged.ref_uncertainty.covs[merged.ref_row[used]], mix.covs[whole.ref_row[used]])

def test_correspondences_leave_a_stage_in_stable_element_order() -> None:
    corr = Correspondences(0, np.zeros(5, np.int64), np.arange(5), np.zeros((5, 3)), np.arange(5.0), "t",
                           element=np.array([2, 0, 2, 1, 0]), n_elements=3)
    ordered = element_ordered(corr)
    assert np.array_equal(ordered.element, [0, 0, 1, 2, 2])
    assert np.array_equal(ordered.ref_element, [1, 4, 3, 0, 2])  # each element's candidates in their given order


def test_shortfall_measures_the_missing_halo() -> None:
    bounds = TileBounds(np.zeros(3), np.ones(3), np.full(3, -0.1), np.full(3, 1.1))
    pos = np.array([[0.5, 0.5, 0.5], [0.95, 0.5, 0.5], [1.05, 0.5, 0.5]])  # the last is halo: not checked
    assert bounds.shortfall(pos, 0.1) == 0.0
    assert bounds.shortfall(pos, 0.3) == pytest.approx(0.15)


@pytest.mark.parametrize("halo", [0.0, 0.02, 0.05, 0.2])
def test_dense_cells_prove_the_same_shortfall_as_a_full_search(halo: float) -> None:
    """The k-nearest shortfall from the cell proof plus a search of the rest equals a search of every point, on a
    clustered cloud (dense patches and sparse strays) whatever the halo."""
    from gdt_pipeline.geometry import knn_reach
    from gdt_pipeline.plugins import StageContext

    rng = np.random.default_rng(7)
    dense = rng.normal(0.5, 0.05, size=(20_000, 3))
    sparse = rng.uniform(-halo, 1 + halo, size=(300, 3))
    pts = np.vstack([dense, sparse])
    bounds = TileBounds(np.zeros(3), np.ones(3), np.full(3, -halo), np.full(3, 1 + halo))
    inside = np.all((pts >= bounds.lower) & (pts <= bounds.upper), axis=1)
    pts = pts[inside]
    full = bounds.shortfall(pts, knn_reach(pts, 20))
    ctx = StageContext(stage=None, params=None, slots={}, epoch=None, rng=None, seed=0, log=None,  # type: ignore
                       tile=bounds)
    ctx.k_nearest(pts, 20)
    assert ctx.shortfalls == [pytest.approx(full, abs=0)]
    proven = bounds.proven_knn(pts, 20)
    if halo >= 0.05:
        assert proven.mean() > 0.5  # most of a dense patch needs no second search
    core = np.all((pts >= 0) & (pts <= 1), axis=1)
    assert np.all(knn_reach(pts, 20)[proven & core] <= halo + 1e-12)


def _plan(registry: object, names: list[str]) -> list[StagePlan]:
    return [StagePlan(i, registry.get(n), registry.get(n).params.model_validate(
        {"tau": 1.0} if n == "fixed" else {"profile": "structured_light"} if n == "sensor_model" else {}))
        for i, n in enumerate(names)]


def test_chain_runs_keep_whole_epoch_stages_apart(registry: object) -> None:
    chain = _plan(registry, ["sensor_model", "sensor_frustum", "auto", "bhattacharyya", "fixed",
                             "calibrated_threshold", "most_reliable"])
    runs = [[st.spec.name for st in run] for run in chain_runs(chain, tiled=True)]
    assert runs == [["sensor_model"], ["sensor_frustum"], ["auto", "bhattacharyya", "fixed"],
                    ["calibrated_threshold"], ["most_reliable"]]
    # a stage whose reach depends on data starts a new run after a stage that changes that data
    runs = [[st.spec.name for st in run] for run in chain_runs(_plan(registry, ["sensor_model", "auto"]), True)]
    assert runs == [["sensor_model"], ["auto"]]
    assert len(chain_runs(chain, tiled=False)) == len(chain)


def test_take_dataset_keeps_a_mesh_valid() -> None:
    from gdt_pipeline.tiling import take_dataset

    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    ds = Dataset("m", "as-designed", verts, faces=np.array([[0, 1, 2], [1, 3, 2]]),
                 uncertainty=BoxUncertainty(np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2]])))
    cut = take_dataset(ds, np.array([1]))
    assert cut.n_elements == 1 and len(cut.points) == 3
    assert np.array_equal(cut.points[cut.faces[0]], verts[[1, 3, 2]])
    assert np.array_equal(cut.uncertainty.half_widths, [[0.2, 0.2, 0.2]])
    assert dataclasses.replace(cut).name == "m"


def test_facet_samples_do_not_depend_on_the_other_facets() -> None:
    from scipy.stats import kstest

    from stages.correspondence.directed import query_samples

    rng = np.random.default_rng(6)
    verts = rng.uniform(0, 1, (600, 3))
    faces = rng.integers(0, 600, (400, 3))
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    mesh = Dataset("m", "as-is", verts, faces=faces)
    pos, element = query_samples(mesh, 11, 50.0, 64)
    keep = np.sort(rng.choice(len(faces), len(faces) // 3, replace=False))
    from gdt_pipeline.tiling import take_dataset

    sub_pos, sub_element = query_samples(take_dataset(mesh, keep), 11, 50.0, 64)
    assert np.array_equal(pos[np.isin(element, keep)], sub_pos)  # a tile samples its facets as the epoch does
    assert np.array_equal(keep[sub_element], element[np.isin(element, keep)])
    # and the samples are uniform on their facets: barycentric u of each sample against U(0, 1) for u + v <= 1
    tri = verts[faces[element]]
    e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], pos - tri[:, 0]
    gram = np.stack([np.stack([np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2)], -1),
                     np.stack([np.einsum("ij,ij->i", e1, e2), np.einsum("ij,ij->i", e2, e2)], -1)], 1)
    uv = np.linalg.solve(gram, np.stack([np.einsum("ij,ij->i", e1, d), np.einsum("ij,ij->i", e2, d)], -1)[..., None])
    u, v = uv[:, 0, 0], uv[:, 1, 0]
    assert np.all(u >= -1e-9) and np.all(v >= -1e-9) and np.all(u + v <= 1 + 1e-9)
    assert kstest(1 - (1 - u) ** 2, "uniform").pvalue > 0.01  # u has density 2(1 - u) on a uniform triangle
    assert query_samples(mesh, 12, 50.0, 64)[0][0].tolist() != pos[0].tolist()  # the seed matters


def test_a_tile_takes_the_reach_of_the_elements_near_it() -> None:
    """Per-element reaches: a tile far from the one wide-reaching element keeps a narrow halo; a tile near it (within
    the widest reach) takes the wide one."""
    from gdt_pipeline.runner.halos import StageReach, tile_reaches

    pos = np.column_stack([np.linspace(0.05, 9.95, 100), np.full(100, 0.5), np.full(100, 0.5)])
    reach = np.full(100, 0.01)
    reach[0] = 0.4  # one grazing point at x = 0.05
    grid = grid_for([pos], 1.0)
    index = [CellIndex(grid, pos)]
    reaches = [StageReach(0.4, (reach,))]
    near = tile_reaches(reaches, *grid.bounds(int(grid.cell(pos[:1])[0])), index)
    far = tile_reaches(reaches, *grid.bounds(int(grid.cell(pos[-1:])[0])), index)
    assert near == [0.4] and far == [0.01]
    shared = tile_reaches([StageReach(0.4, (None,))], *grid.bounds(int(grid.cell(pos[-1:])[0])), index)
    assert shared == [0.4]


@pytest.mark.parametrize("on_disk", [False, True])
@pytest.mark.parametrize("mixed", [False, True])
def test_uncertainty_merged_as_tiles_finish_equals_the_concatenation(mixed: bool, on_disk: bool, tmp_path: Path
                                                                      ) -> None:
    """Covariances written into place tile by tile, in memory or in a scratch file, are the concatenation put in
    element order, also when one tile's model (a shared row) cannot be written into place."""
    from gdt_pipeline.tiling.merge import RecentSink, UncertaintyPiece, merge_recent

    rng = np.random.default_rng(3)
    n = 50
    a = rng.normal(size=(n, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2) + np.eye(3)
    ds = Dataset(name="s", role="as-is", points=rng.normal(size=(n, 3)))
    members = [np.sort(rng.permutation(n)[:20]), None, None]
    rest = np.setdiff1d(np.arange(n), members[0])
    members[1], members[2] = rest[:10], rest[10:]
    pieces = [UncertaintyPiece(GaussianUncertainty(cov[m], dof=4.0), len(m)) for m in members]
    if mixed:
        cov[members[2]] = np.eye(3) * 2.0
        pieces[2] = UncertaintyPiece(GaussianUncertainty(np.eye(3)[None] * 2.0, dof=4.0), len(members[2]))
    order = ElementOrder.check("s", members, n)
    want = merge_recent(ds, pieces, order)
    sink = RecentSink([n], tmp_path if on_disk else None)
    held = []
    for piece, m in zip(pieces, members, strict=True):
        one = [piece]
        sink.absorb(one, [m])
        held.append(one[0])
    assert (held[2] is not None) == mixed and held[0] is None
    got = sink.merged(ds, 0, held, members, order)
    assert np.array_equal(got.uncertainty.cov, want.uncertainty.cov) and np.array_equal(got.uncertainty.cov, cov)
    assert got.uncertainty.dof == 4.0
    assert isinstance(got.uncertainty.cov, MappedRows) == (on_disk and not mixed)
    assert not got.uncertainty.cov.flags.writeable and not sink.files and list(tmp_path.iterdir()) == []


def test_covariances_kept_on_a_full_disk_name_the_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A scratch folder without room for the covariances stops the run before any tile writes there, naming the
    folder and the room it needs."""
    import errno
    import os

    from gdt_pipeline.tiling.merge import RecentSink, UncertaintyPiece

    def full(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "posix_fallocate", full)
    sink = RecentSink([10_000_000], tmp_path)
    piece = UncertaintyPiece(GaussianUncertainty(np.tile(np.eye(3), (4, 1, 1))), 4)
    with pytest.raises(GdtError, match=rf"{tmp_path}.*0\.72 GB.*No space left on device.*TMPDIR"):
        sink.absorb([piece], [np.arange(4)])
    assert not sink.files and list(tmp_path.iterdir()) == []


def test_tile_index_arrays_are_int32_and_hold_what_a_scan_of_every_position_finds() -> None:
    """The tiles' members, the box index and the merge order are 4 B an element (int32 below 2³¹ rows), and still
    name exactly the elements a brute-force scan of every position finds, a chunk of cells at a time included."""
    from gdt_pipeline.tiling import grid as grid_module

    rng = np.random.default_rng(6)
    pos = rng.uniform(0, 1, (grid_module.CELL_CHUNK + 1_234, 3))
    grid = grid_for([pos], 0.3)
    cells = grid.cell(pos)
    assert cells.dtype == np.int32
    ijk = np.clip(np.floor((pos - grid.origin) / grid.size).astype(np.int64), 0, np.asarray(grid.shape) - 1)
    assert np.array_equal(cells, ijk[:, 0] + grid.shape[0] * (ijk[:, 1] + grid.shape[1] * ijk[:, 2]))
    members = members_of([CellIndex(grid, pos)])
    for tile, (ids,) in members.items():
        assert ids.dtype == np.int32 and np.array_equal(ids, np.flatnonzero(cells == tile))
    lo, hi = np.array([0.2, 0.1, 0.4]), np.array([0.7, 0.35, 0.9])
    found = CellIndex(grid, pos).query(lo, hi)
    assert found.dtype == np.int32
    assert np.array_equal(found, np.flatnonzero(np.all((pos >= lo) & (pos <= hi), axis=1)))
    order = ElementOrder.check("scan", [m[0] for m in members.values()], len(pos))
    assert order.position.dtype == np.int32
    assert np.array_equal(np.concatenate([m[0] for m in members.values()])[order.position], np.arange(len(pos)))
