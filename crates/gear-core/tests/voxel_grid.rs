//! The shared grid, point-to-voxel mapping, set operations and dilation against direct
//! definitions.

use std::collections::BTreeSet;

use gear_core::voxel::{
    difference, dilate_dense, dilate_keys, intersection, occupancy_dense, occupancy_keys, union,
    voxel_indices, GridSpec,
};
use gear_core::GearError;

fn message<T>(r: gear_core::Result<T>) -> String {
    match r.err().expect("should fail") {
        GearError::InvalidInput(m) => m,
        other => panic!("expected InvalidInput, got {other:?}"),
    }
}

#[test]
fn grid_encloses_all_sets_from_their_min_corner() {
    let a = [[0.5f32, 2.0, -1.0], [1.0, 2.5, 0.0]];
    let b = [[0.1f32, 3.0, -0.5]];
    let grid = GridSpec::enclosing(&[&a, &b, &[]], 0.25).unwrap();
    assert_eq!(grid.origin, [0.1f32 as f64, 2.0, -1.0]);
    // Extents 0.9, 1.0, 1.0 over 0.25: the max corner falls in voxel 3, 4, 4.
    assert_eq!(grid.shape, [4, 5, 5]);
    let all: Vec<[f32; 3]> = a.iter().chain(&b).copied().collect();
    for v in voxel_indices(&grid, &all).unwrap() {
        assert!(grid.key(v).is_some(), "{v:?} outside {:?}", grid.shape);
    }
    let outside = [[-5.0f32, 2.0, -1.0]];
    assert_eq!(voxel_indices(&grid, &outside).unwrap()[0][0], -21);
}

#[test]
fn voxel_indices_floor_the_offset_from_the_origin_for_small_and_large_sets() {
    // A few hundred points are indexed on the calling thread, tens of thousands in the pool:
    // both give floor((p - origin) / size) in f64, inside the grid or not.
    let mut rng = fastrand::Rng::with_seed(9);
    let grid = GridSpec::new([-0.3, 0.1, 2.0], 0.07, [20, 30, 10]).unwrap();
    for n in [1, 300, 40_000] {
        let points: Vec<[f32; 3]> = (0..n)
            .map(|_| [rng.f32() * 3.0 - 1.0, rng.f32() * 2.0, rng.f32() + 1.8])
            .collect();
        let found = voxel_indices(&grid, &points).unwrap();
        assert_eq!(found.len(), n);
        for (p, v) in points.iter().zip(&found) {
            let want: [i64; 3] = std::array::from_fn(|a| {
                ((f64::from(p[a]) - grid.origin[a]) / grid.voxel_size).floor() as i64
            });
            assert_eq!(*v, want);
        }
    }
}

#[test]
fn dense_and_sparse_occupancy_agree_and_ignore_outside_points() {
    let mut rng = fastrand::Rng::with_seed(5);
    let points: Vec<[f32; 3]> = (0..2000)
        .map(|_| [rng.f32(), rng.f32() * 2.0, rng.f32() * 0.5])
        .collect();
    let grid = GridSpec::enclosing(&[&points], 0.07).unwrap();
    let dense = occupancy_dense(&grid, &points).unwrap();
    let keys = occupancy_keys(&grid, &points).unwrap();
    let expected: BTreeSet<i64> = points
        .iter()
        .map(|&p| grid.key(grid.voxel_of(p)).unwrap())
        .collect();
    assert_eq!(keys, expected.iter().copied().collect::<Vec<_>>());
    let from_dense: Vec<i64> = (0..dense.len() as i64)
        .filter(|&k| dense[k as usize])
        .collect();
    assert_eq!(from_dense, keys);
    let far = [[100.0f32, 0.0, 0.0], [0.5, -3.0, 0.2]];
    assert!(occupancy_keys(&grid, &far).unwrap().is_empty());
    assert!(!occupancy_dense(&grid, &far).unwrap().contains(&true));
}

#[test]
fn bad_grids_are_rejected_with_the_argument_named() {
    let p = [[0.0f32, 0.0, 0.0], [1.0, 1.0, 1.0]];
    for v in [0.0, -0.1, f64::NAN, f64::INFINITY] {
        assert!(message(GridSpec::enclosing(&[&p], v)).starts_with("voxel_size:"));
    }
    assert!(message(GridSpec::enclosing(&[&[], &[]], 0.1)).starts_with("point_sets:"));
    let nan = [[0.0f32, f32::NAN, 0.0]];
    assert!(message(GridSpec::enclosing(&[&p, &nan], 0.1)).starts_with("point_sets[1]: row 0"));
    assert!(message(GridSpec::enclosing(&[&p], 1e-7)).starts_with("voxel_size:"));
    assert!(
        message(GridSpec::new([0.0; 3], 1.0, [1 << 30, 1 << 30, 1 << 10])).starts_with("shape:")
    );
}

#[test]
fn set_operations_match_btreeset() {
    let mut rng = fastrand::Rng::with_seed(6);
    let mut draw = || -> BTreeSet<i64> { (0..300).map(|_| rng.i64(0..500)).collect() };
    let (a, b) = (draw(), draw());
    let va: Vec<i64> = a.iter().copied().collect();
    let vb: Vec<i64> = b.iter().copied().collect();
    let to_vec = |s: BTreeSet<i64>| s.into_iter().collect::<Vec<_>>();
    assert_eq!(intersection(&va, &vb), to_vec(&a & &b));
    assert_eq!(difference(&va, &vb), to_vec(&a - &b));
    assert_eq!(union(&va, &vb), to_vec(&a | &b));
    assert!(intersection(&va, &[]).is_empty());
    assert_eq!(difference(&va, &[]), va);
}

/// Dilation by definition: every cell within the cube around an occupied cell, clipped.
fn dilate_by_definition(occ: &[bool], [x, y, z]: [usize; 3], r: usize) -> Vec<bool> {
    let mut out = vec![false; occ.len()];
    let r = r as i64;
    for (c, _) in occ.iter().enumerate().filter(|(_, &o)| o) {
        let v = [(c / (y * z)) as i64, ((c / z) % y) as i64, (c % z) as i64];
        for i in (v[0] - r).max(0)..=(v[0] + r).min(x as i64 - 1) {
            for j in (v[1] - r).max(0)..=(v[1] + r).min(y as i64 - 1) {
                for k in (v[2] - r).max(0)..=(v[2] + r).min(z as i64 - 1) {
                    out[(i as usize * y + j as usize) * z + k as usize] = true;
                }
            }
        }
    }
    out
}

#[test]
fn dilation_matches_its_definition_dense_and_sparse() {
    let mut rng = fastrand::Rng::with_seed(9);
    for shape in [[9, 12, 15], [1, 7, 3], [20, 3, 40]] {
        let occ: Vec<bool> = (0..shape.iter().product())
            .map(|_| rng.f32() < 0.02)
            .collect();
        let keys: Vec<i64> = (0..occ.len() as i64).filter(|&k| occ[k as usize]).collect();
        for r in [0, 1, 2, 5, 50] {
            let expected = dilate_by_definition(&occ, shape, r);
            assert_eq!(
                dilate_dense(&occ, shape, r),
                expected,
                "dense {shape:?} r={r}"
            );
            let expected_keys: Vec<i64> = (0..occ.len() as i64)
                .filter(|&k| expected[k as usize])
                .collect();
            assert_eq!(
                dilate_keys(&keys, shape, r).unwrap(),
                expected_keys,
                "sparse r={r}"
            );
        }
    }
}

#[test]
fn sparse_dilation_refuses_an_absurd_output() {
    let shape = [1 << 20, 1 << 20, 1 << 20];
    // Interior voxels far apart: (1000 i + 5, i + 7, 9).
    let keys: Vec<i64> = (1..=1000)
        .map(|i| ((i * 1000 + 5) << 40) + ((i + 7) << 20) + 9)
        .collect();
    // 1000 voxels x (2 * 2^17 + 1) along z is past the bound already in the first pass.
    assert!(message(dilate_keys(&keys, shape, 1 << 17)).starts_with("radius:"));
    assert_eq!(dilate_keys(&keys, shape, 1).unwrap().len(), 1000 * 27);
}
