//! Components (dense and sparse) against a breadth-first flood fill.

use std::collections::VecDeque;

use gear_core::voxel::{components_dense, components_keys, Connectivity};

/// Reference labelling: flood fill in C order, then labels renumbered by (size desc, first
/// voxel), which is the documented order.
fn flood_fill(occ: &[bool], [x, y, z]: [usize; 3], conn: Connectivity) -> (Vec<i32>, Vec<i64>) {
    let mut offsets = Vec::new();
    for dx in -1i64..=1 {
        for dy in -1i64..=1 {
            for dz in -1i64..=1 {
                let manhattan = dx.abs() + dy.abs() + dz.abs();
                if manhattan == 1 || (conn == Connectivity::TwentySix && manhattan > 0) {
                    offsets.push([dx, dy, dz]);
                }
            }
        }
    }
    let mut comp = vec![0usize; occ.len()];
    let mut sizes = Vec::new();
    for start in 0..occ.len() {
        if !occ[start] || comp[start] != 0 {
            continue;
        }
        sizes.push(0i64);
        let id = sizes.len();
        comp[start] = id;
        let mut queue = VecDeque::from([start]);
        while let Some(c) = queue.pop_front() {
            sizes[id - 1] += 1;
            let v = [(c / (y * z)) as i64, ((c / z) % y) as i64, (c % z) as i64];
            for o in &offsets {
                let n = [v[0] + o[0], v[1] + o[1], v[2] + o[2]];
                if n.iter()
                    .zip([x, y, z])
                    .any(|(&a, s)| a < 0 || a >= s as i64)
                {
                    continue;
                }
                let ni = (n[0] as usize * y + n[1] as usize) * z + n[2] as usize;
                if occ[ni] && comp[ni] == 0 {
                    comp[ni] = id;
                    queue.push_back(ni);
                }
            }
        }
    }
    // Components were found in order of their first voxel, so a stable sort by size is the
    // documented order.
    let mut order: Vec<usize> = (0..sizes.len()).collect();
    order.sort_by_key(|&c| std::cmp::Reverse(sizes[c]));
    let mut label_of = vec![0i32; sizes.len() + 1];
    for (rank, &c) in order.iter().enumerate() {
        label_of[c + 1] = rank as i32 + 1;
    }
    let labels = comp.iter().map(|&c| label_of[c]).collect();
    (labels, order.iter().map(|&c| sizes[c]).collect())
}

fn check(occ: &[bool], shape: [usize; 3], conn: Connectivity) {
    let (labels, sizes) = flood_fill(occ, shape, conn);
    let dense = components_dense(occ, shape, conn);
    assert_eq!(dense.sizes, sizes, "dense sizes, shape {shape:?} {conn:?}");
    assert_eq!(
        dense.labels, labels,
        "dense labels, shape {shape:?} {conn:?}"
    );

    let keys: Vec<i64> = (0..occ.len() as i64).filter(|&k| occ[k as usize]).collect();
    let sparse = components_keys(&keys, shape, conn);
    assert_eq!(sparse.sizes, sizes, "sparse sizes");
    let expected: Vec<i32> = keys.iter().map(|&k| labels[k as usize]).collect();
    assert_eq!(sparse.labels, expected, "sparse labels");
}

fn random_grid(rng: &mut fastrand::Rng, shape: [usize; 3], fill: f32) -> Vec<bool> {
    (0..shape.iter().product())
        .map(|_| rng.f32() < fill)
        .collect()
}

/// Random grids (seeded with `seed`) of each shape at each fill fraction against flood fill,
/// in both connectivities.
fn check_random_grids(seed: u64, shapes: &[[usize; 3]], fills: &[f32]) {
    let mut rng = fastrand::Rng::with_seed(seed);
    for &shape in shapes {
        for &fill in fills {
            let occ = random_grid(&mut rng, shape, fill);
            check(&occ, shape, Connectivity::TwentySix);
            check(&occ, shape, Connectivity::Six);
        }
    }
}

#[test]
fn random_grids_match_flood_fill() {
    let shapes = [
        [7, 9, 11],
        [20, 17, 13],
        [1, 30, 70],
        [33, 2, 1],
        [5, 5, 130],
    ];
    check_random_grids(7, &shapes, &[0.03, 0.1, 0.3, 0.6]);
}

#[test]
fn grid_large_enough_for_parallel_slabs_matches_flood_fill() {
    check_random_grids(8, &[[40, 24, 70]], &[0.08, 0.25]);
}

#[test]
fn long_lines_joined_by_sweeping_match_flood_fill() {
    // Lines longer than 4096 cells are not indexed cell by cell; the sweep joins them.
    check_random_grids(10, &[[4, 3, 5000]], &[0.05, 0.4]);
}

#[test]
fn diagonal_contacts_join_only_with_26_connectivity() {
    let shape = [3, 3, 3];
    let idx = |x: usize, y: usize, z: usize| (x * 3 + y) * 3 + z;
    for (a, b) in [
        (idx(0, 0, 0), idx(1, 1, 1)), // corner
        (idx(0, 0, 0), idx(0, 1, 1)), // edge
        (idx(2, 0, 1), idx(1, 1, 0)), // edge across planes
        (idx(0, 2, 0), idx(1, 1, 1)), // corner, y decreasing
    ] {
        let mut occ = vec![false; 27];
        occ[a] = true;
        occ[b] = true;
        assert_eq!(
            components_dense(&occ, shape, Connectivity::TwentySix).sizes,
            vec![2]
        );
        assert_eq!(
            components_dense(&occ, shape, Connectivity::Six).sizes,
            vec![1, 1]
        );
        check(&occ, shape, Connectivity::TwentySix);
        check(&occ, shape, Connectivity::Six);
    }
}

#[test]
fn equal_sizes_are_ordered_by_first_voxel_and_boundary_components_count() {
    // Three single voxels on the grid's corners and faces, and a 2-voxel bar on the far face.
    let shape = [4, 4, 4];
    let idx = |x: usize, y: usize, z: usize| (x * 4 + y) * 4 + z;
    let mut occ = vec![false; 64];
    for c in [
        idx(3, 3, 3),
        idx(0, 0, 0),
        idx(0, 3, 0),
        idx(3, 0, 2),
        idx(3, 0, 3),
    ] {
        occ[c] = true;
    }
    let found = components_dense(&occ, shape, Connectivity::TwentySix);
    assert_eq!(found.sizes, vec![2, 1, 1, 1]);
    assert_eq!(found.labels[idx(3, 0, 2)], 1);
    assert_eq!(found.labels[idx(0, 0, 0)], 2);
    assert_eq!(found.labels[idx(0, 3, 0)], 3);
    assert_eq!(found.labels[idx(3, 3, 3)], 4);
    check(&occ, shape, Connectivity::TwentySix);
}

#[test]
fn empty_full_and_degenerate_grids() {
    for shape in [[4, 5, 6], [0, 5, 5], [5, 0, 5], [5, 5, 0], [1, 1, 1]] {
        let cells = shape.iter().product();
        let empty = vec![false; cells];
        let found = components_dense(&empty, shape, Connectivity::TwentySix);
        assert!(found.sizes.is_empty() && found.labels.iter().all(|&l| l == 0));
        assert!(components_keys(&[], shape, Connectivity::Six)
            .sizes
            .is_empty());
        let full = vec![true; cells];
        check(&full, shape, Connectivity::Six);
        check(&full, shape, Connectivity::TwentySix);
    }
}
