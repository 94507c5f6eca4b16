"""gear.geometry against scipy: KNN vs cKDTree, components vs ndimage.label, dilation vs
ndimage.binary_dilation; dense and sparse grids give identical results; bad input is refused."""

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from gear import geometry
from gear.geometry import Occupancy, components, dilate, knn, voxel_grid

# ---------------------------------------------------------------------------------------------
# KNN


def check_knn(points, k, queries=None):
    """Indices and distances against cKDTree, robust to ties: every returned index must be at
    its reported distance, and the reported distances must be the reference k smallest."""
    idx, dist = knn(points, k, queries)
    ref_pts = np.asarray(points, dtype=np.float32).astype(np.float64)
    self_query = queries is None
    q = ref_pts if self_query else np.asarray(queries, dtype=np.float32).astype(np.float64)
    assert idx.dtype == np.int64 and dist.dtype == np.float32
    assert idx.shape == dist.shape == (len(q), k)
    if self_query:
        ref_d, _ = cKDTree(ref_pts).query(q, k + 1)
        ref_d = ref_d.reshape(len(q), k + 1)[:, 1:]  # the point itself (or a twin) at 0
        assert np.all(idx != np.arange(len(q))[:, None]), "a point is its own neighbour"
    else:
        ref_d, _ = cKDTree(ref_pts).query(q, k)
        ref_d = ref_d.reshape(len(q), k)
    true_d = np.linalg.norm(ref_pts[idx] - q[:, None, :], axis=2)
    np.testing.assert_allclose(dist, true_d, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dist, ref_d, rtol=1e-5, atol=1e-6)
    assert np.all(np.diff(dist, axis=1) >= 0), "not sorted nearest first"
    assert all(len(set(row)) == k for row in idx.tolist()), "repeated neighbour"
    return idx, dist


@pytest.mark.parametrize("k", [1, 3, 16])
def test_knn_random_self_matches_ckdtree(k):
    points = np.random.default_rng(k).normal(size=(3000, 3)).astype(np.float32)
    check_knn(points, k)


def test_knn_external_queries_float64_input():
    rng = np.random.default_rng(1)
    points = rng.uniform(-1, 1, (2000, 3))  # float64: converted once
    queries = rng.uniform(-2, 2, (500, 3))
    check_knn(points, 5, queries)


def test_knn_accepts_torch_centres_with_grad():
    torch = pytest.importorskip("torch")
    centres = torch.randn(500, 3, requires_grad=True)
    idx, dist = knn(centres, 3)
    ref_idx, ref_dist = knn(centres.detach().numpy(), 3)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_array_equal(dist, ref_dist)
    check_knn(centres.detach().numpy(), 3)


def test_knn_k_equals_n_minus_one():
    points = np.random.default_rng(2).random((60, 3), dtype=np.float32)
    check_knn(points, 59)
    check_knn(points, 60, points[:7])


def test_knn_identical_points():
    points = np.full((100, 3), 0.5, dtype=np.float32)
    _, dist = check_knn(points, 8)
    assert np.all(dist == 0)


def test_knn_points_on_a_line_with_ties():
    t = np.arange(200, dtype=np.float32)
    points = np.stack([t, -t, 0.5 * t], axis=1)
    check_knn(points, 1)
    check_knn(points, 4)
    check_knn(points, 199)


def test_knn_empty_inputs():
    idx, dist = knn(np.zeros((0, 3), np.float32), 4)
    assert idx.shape == dist.shape == (0, 4)
    idx, dist = knn(np.zeros((5, 3), np.float32), 2, np.zeros((0, 3)))
    assert idx.shape == (0, 2)


@pytest.mark.parametrize(
    ("points", "k", "queries", "match"),
    [
        (np.zeros((5, 3)), 0, None, "k: must be at least 1"),
        (np.zeros((5, 3)), -2, None, "k: must be at least 1"),
        (np.zeros((5, 3)), 2.5, None, "k: expected an integer"),
        (np.zeros((5, 3)), 5, None, r"k: asks for 5 .* only 4 .*self excluded"),
        (np.zeros((5, 3)), 6, np.zeros((2, 3)), r"k: asks for 6 .* only 5"),
        (np.array([[0, 0, np.nan]] * 3), 1, None, "points: row 0 has a non-finite"),
        (np.zeros((5, 3)), 1, np.array([[np.inf, 0, 0]]), "queries: row 0 has a non-finite"),
        (np.zeros((5, 2)), 1, None, r"points: expected shape \[N, 3\]"),
    ],
)
def test_knn_bad_input_names_the_argument(points, k, queries, match):
    with pytest.raises(ValueError, match=match):
        knn(points, k, queries)


def test_nearest_tree_matches_ckdtree_over_many_calls():
    """One tree, queried again and again with small and large sets (the calling thread's path
    and the pool's): scipy's shapes and order, distances to float32 precision, every index at
    its distance, and `data` the points in float64."""
    rng = np.random.default_rng(5)
    points = rng.uniform(-1, 1, (3000, 3))
    tree = geometry.NearestTree(points)
    reference = cKDTree(points.astype(np.float32).astype(np.float64))
    assert len(tree) == 3000 and tree.data.dtype == np.float64
    np.testing.assert_array_equal(tree.data, points)
    for count, k in [(1, 1), (200, 1), (2000, 1), (200, 4), (2000, 2)]:
        queries = rng.uniform(-1.5, 1.5, (count, 3))
        dist, idx = tree.query(queries, k=k)
        ref_dist, _ = reference.query(queries, k=k)
        shape = (count,) if k == 1 else (count, k)
        assert dist.shape == idx.shape == shape
        assert dist.dtype == np.float64 and idx.dtype == np.int64
        np.testing.assert_allclose(dist, ref_dist, rtol=1e-5, atol=1e-6)
        at = np.linalg.norm(tree.data[idx] - (queries if k == 1 else queries[:, None]), axis=-1)
        np.testing.assert_allclose(dist, at, rtol=1e-5, atol=1e-6)


def test_nearest_tree_refuses_bad_input():
    with pytest.raises(ValueError, match="points: row 1 has a non-finite"):
        geometry.NearestTree(np.array([[0, 0, 0], [0, np.nan, 0]]))
    tree = geometry.NearestTree(np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"k: asks for 4 .* only 3"):
        tree.query(np.zeros((1, 3)), k=4)
    with pytest.raises(ValueError, match="k: must be at least 1"):
        tree.query(np.zeros((1, 3)), k=0)
    with pytest.raises(ValueError, match="queries: row 0 has a non-finite"):
        tree.query(np.array([[np.inf, 0, 0]]))
    with pytest.raises(ValueError, match=r"queries: expected shape \[N, 3\]"):
        tree.query(np.zeros((2, 2)))
    dist, idx = tree.query(np.zeros((0, 3)))
    assert dist.shape == idx.shape == (0,)


# ---------------------------------------------------------------------------------------------
# Components

STRUCTURES = {26: np.ones((3, 3, 3), bool), 6: ndimage.generate_binary_structure(3, 1)}


def scipy_components(occ, connectivity):
    """scipy's labels renumbered to the documented order: size descending, then first voxel
    in C order (scipy numbers components by first voxel, so a stable sort does it)."""
    ref, n = ndimage.label(occ, structure=STRUCTURES[connectivity])
    counts = np.bincount(ref.ravel(), minlength=n + 1)[1:]
    order = np.argsort(-counts, kind="stable")
    relabel = np.zeros(n + 1, np.int32)
    relabel[order + 1] = np.arange(1, n + 1, dtype=np.int32)
    return relabel[ref], counts[order]


def check_components(occ, connectivity):
    labels, sizes = components(occ, connectivity)
    ref_labels, ref_sizes = scipy_components(occ, connectivity)
    assert labels.dtype == np.int32 and labels.shape == occ.shape
    assert sizes.dtype == np.int64
    np.testing.assert_array_equal(sizes, ref_sizes)
    np.testing.assert_array_equal(labels, ref_labels)
    # The sparse path on the same voxels gives the same labels, key by key.
    sparse = Occupancy(occ.shape, keys=np.flatnonzero(occ))
    sparse_labels, sparse_sizes = components(sparse, connectivity)
    np.testing.assert_array_equal(sparse_sizes, ref_sizes)
    np.testing.assert_array_equal(sparse_labels, ref_labels.ravel()[sparse.keys])
    return labels, sizes


@pytest.mark.parametrize("connectivity", [26, 6])
@pytest.mark.parametrize(("shape", "fill"), [((17, 23, 29), 0.04), ((30, 20, 40), 0.25),
                                             ((9, 64, 3), 0.5), ((1, 1, 70), 0.5)])
def test_components_random_grids_match_scipy(shape, fill, connectivity):
    occ = np.random.default_rng(int(fill * 100)).random(shape) < fill
    check_components(occ, connectivity)


def test_one_voxel_components_and_boundary_contacts():
    occ = np.zeros((6, 7, 8), bool)
    occ[0, 0, 0] = occ[5, 6, 7] = occ[2, 3, 4] = True  # single voxels, two at corners
    occ[:, 6, 0] = True  # a bar along the whole x edge
    occ[3, 0, :] = True  # a bar along z on the y = 0 face
    labels, sizes = check_components(occ, 26)
    assert sizes.tolist() == [8, 6, 1, 1, 1]
    assert labels[3, 0, 5] == 1 and labels[0, 6, 0] == 2
    assert [labels[0, 0, 0], labels[2, 3, 4], labels[5, 6, 7]] == [3, 4, 5]
    check_components(occ, 6)


def test_diagonal_only_contacts_need_26_connectivity():
    occ = np.zeros((4, 4, 4), bool)
    occ[0, 0, 0] = occ[1, 1, 1] = occ[2, 2, 1] = occ[3, 2, 2] = True  # corner, edge, corner
    assert components(occ, 26)[1].tolist() == [4]
    assert components(occ, 6)[1].tolist() == [1, 1, 1, 1]
    check_components(occ, 26)
    check_components(occ, 6)


def test_empty_grid():
    labels, sizes = check_components(np.zeros((5, 6, 7), bool), 26)
    assert sizes.size == 0 and not labels.any()


def test_components_bad_connectivity_and_shape():
    with pytest.raises(ValueError, match="connectivity: must be 6 or 26"):
        components(np.ones((2, 2, 2), bool), 18)
    with pytest.raises(ValueError, match="occ: expected a 3-D"):
        components(np.ones((2, 2), bool))


# ---------------------------------------------------------------------------------------------
# Grids, dilation, set operations; dense vs sparse


def two_sets(seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(0, 0.3, (1500, 3)).astype(np.float32)
    b = (rng.normal(0, 0.3, (1500, 3)) + np.array([0.4, 0.0, -0.2])).astype(np.float32)
    return a, b


def test_grid_origin_shape_and_voxel_mapping():
    a, b = two_sets()
    grid = voxel_grid([a, b], 0.05)
    np.testing.assert_array_equal(grid.origin, np.minimum(a.min(0), b.min(0)).astype(np.float64))
    top = np.maximum(a.max(0), b.max(0)).astype(np.float64)
    expected_shape = np.floor((top - grid.origin) / 0.05).astype(int) + 1
    assert grid.shape == tuple(expected_shape)
    for pts, occ in zip([a, b], grid.occupancy, strict=True):
        v = grid.voxel_of(pts)
        ref = np.floor((pts.astype(np.float64) - grid.origin) / 0.05).astype(np.int64)
        np.testing.assert_array_equal(v, ref)
        expected = np.zeros(grid.shape, bool)
        expected[tuple(ref.T)] = True
        np.testing.assert_array_equal(occ.to_dense(), expected)
    centres = grid.centres(grid.voxel_of(a))
    assert np.all(np.abs(centres - a) <= 0.5 * 0.05 + 1e-6)


def test_dense_and_sparse_grids_give_identical_results():
    a, b = two_sets(1)
    dense = voxel_grid([a, b], 0.04)
    sparse = voxel_grid([a, b], 0.04, max_dense_cells=0)
    assert not dense.is_sparse and sparse.is_sparse
    assert dense.shape == sparse.shape and np.array_equal(dense.origin, sparse.origin)
    results = []
    for grid in (dense, sparse):
        occ_a, occ_b = grid.occupancy
        static = dilate(occ_a & occ_b, 1)
        dynamic = occ_a - static
        labels, sizes = components(dynamic, 26)
        probe = np.concatenate([occ_b.coords()[:50], [[-1, 0, 0], [0, 0, 10**6]]])
        results.append(dict(
            contains=occ_a.contains(probe), a=occ_a.keys, union=(occ_a | occ_b).keys,
            static=static.keys, dynamic=dynamic.keys,
            sizes=sizes, point_labels=grid.point_labels(a, labels, dynamic),
        ))
    for key in results[0]:
        np.testing.assert_array_equal(results[0][key], results[1][key], err_msg=key)
    assert results[0]["sizes"].size > 0 and results[0]["point_labels"].any()
    assert results[0]["contains"].any() and not results[0]["contains"][-2:].any()


def test_point_labels_follow_the_voxel_labels():
    a, _ = two_sets(2)
    grid = voxel_grid([a], 0.1)
    labels, _ = components(grid.occupancy[0], 6)
    v = grid.voxel_of(a)
    np.testing.assert_array_equal(grid.point_labels(a, labels), labels[tuple(v.T)])
    far = np.array([[100.0, 0, 0], [-100.0, 0, 0]])
    assert grid.point_labels(far, labels).tolist() == [0, 0]


@pytest.mark.parametrize("radius", [0, 1, 2])
def test_dilation_matches_scipy_dense_and_sparse(radius):
    occ = np.random.default_rng(radius).random((15, 20, 25)) < 0.03
    cube = np.ones((2 * radius + 1,) * 3, bool)
    expected = ndimage.binary_dilation(occ, cube) if radius else occ
    np.testing.assert_array_equal(dilate(occ, radius), expected)
    sparse = Occupancy(occ.shape, keys=np.flatnonzero(occ))
    np.testing.assert_array_equal(dilate(sparse, radius).keys, np.flatnonzero(expected))


def test_set_operations_match_numpy():
    rng = np.random.default_rng(3)
    x, y = rng.random((2, 8, 9, 10)) < 0.3
    for make in (lambda o: Occupancy(o.shape, dense=o),
                 lambda o: Occupancy(o.shape, keys=np.flatnonzero(o))):
        a, b = make(x), make(y)
        np.testing.assert_array_equal((a & b).to_dense(), x & y)
        np.testing.assert_array_equal((a | b).to_dense(), x | y)
        np.testing.assert_array_equal((a - b).to_dense(), x & ~y)
    mixed = Occupancy(x.shape, dense=x) & Occupancy(y.shape, keys=np.flatnonzero(y))
    assert mixed.is_sparse and np.array_equal(mixed.to_dense(), x & y)


@pytest.mark.parametrize(
    ("sets", "size", "match"),
    [
        ([np.zeros((3, 3))], 0.0, "voxel_size: must be a positive"),
        ([np.zeros((3, 3))], -1.0, "voxel_size: must be a positive"),
        ([np.zeros((3, 3))], float("nan"), "voxel_size: must be a positive"),
        ([np.zeros((3, 3)), np.array([[0, np.nan, 0]])], 0.1, r"point_sets\[1\]: row 0"),
        ([np.zeros((0, 3))], 0.1, "point_sets: no points"),
        ([np.array([[0, 0, 0], [1e6, 1e6, 1e6]])], 1e-9, "voxel_size: .* cells"),
        (np.zeros((4, 3)), 0.1, "point_sets: expected a sequence"),
    ],
)
def test_bad_grid_input_names_the_argument(sets, size, match):
    with pytest.raises(ValueError, match=match):
        voxel_grid(sets, size)


@pytest.mark.parametrize("keys", [[3, 1], [1, 1], [-1, 2], [5, 60]])
def test_occupancy_rejects_invalid_keys(keys):
    with pytest.raises(ValueError, match="keys: expected strictly increasing"):
        Occupancy((3, 4, 5), keys=np.array(keys))


def test_sparse_grid_beyond_the_dense_bound():
    # 0.001 voxels over a unit object: 10^9 cells, far past the dense bound -> sparse.
    pts = np.random.default_rng(4).random((5000, 3)).astype(np.float32)
    grid = voxel_grid([pts], 0.001)
    assert grid.is_sparse and grid.cells > geometry.DEFAULT_MAX_DENSE_CELLS
    assert grid.occupancy[0].count == len(np.unique(grid.voxel_of(pts), axis=0))
    labels, sizes = components(grid.occupancy[0])
    assert labels.shape == (grid.occupancy[0].count,) and sizes.sum() == labels.size
    with pytest.raises(ValueError, match="max_cells: a dense"):
        grid.occupancy[0].to_dense()
    with pytest.raises(ValueError, match="radius: must be at least 0"):
        dilate(grid.occupancy[0], -1)


def test_piece_labels_bridge_gaps_under_the_grown_cells():
    """Cells 3 apart along x (a gap of two empty cells) join once grown by one cell; 4 apart
    (three empty cells) stay two pieces; labels follow the sets' points in order."""
    a = np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]])  # cells 0 and 1
    near = np.array([[0.45, 0.05, 0.05]])  # cell 4: 3 past a's last cell
    far = np.array([[0.55, 0.05, 0.05]])  # cell 5: 4 past it
    of_a, of_near = geometry.piece_labels([a, near], 0.1)
    assert of_a.tolist() == [1, 1] and of_near.tolist() == [1]
    of_a, of_far = geometry.piece_labels([a, far], 0.1)
    assert of_a.tolist() == [1, 1] and of_far.tolist() == [2]
    assert geometry.piece_labels([a, far], 0.1, grow=2)[1].tolist() == [1]
