//! KNN against brute force: random, duplicate and collinear sets, self-exclusion, external
//! queries, a tree kept for many queries, and the error cases.

use gear_core::knn::{knn, NearestTree, Neighbours, Queries};
use gear_core::GearError;

fn random_points(rng: &mut fastrand::Rng, n: usize, scale: f32) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| [rng.f32() * scale, rng.f32() * scale, rng.f32() * scale])
        .collect()
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3)
        .map(|i| (f64::from(a[i]) - f64::from(b[i])).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Checks row `row` of `found`, the neighbours of `q`, against brute force: distinct valid
/// indices (never `skip`), each at the distance reported, sorted, and the reported distances
/// equal to the true k smallest.
fn check_row(
    points: &[[f32; 3]],
    q: [f32; 3],
    skip: Option<usize>,
    found: &Neighbours,
    row: usize,
) {
    let k = found.k;
    let idx = &found.indices[row * k..(row + 1) * k];
    let d = &found.distances[row * k..(row + 1) * k];
    let mut truth: Vec<f64> = (0..points.len())
        .filter(|&i| Some(i) != skip)
        .map(|i| dist(points[i], q))
        .collect();
    truth.sort_by(f64::total_cmp);
    let tol = |x: f64| 1e-5 * x.max(1.0);
    let mut seen = std::collections::HashSet::new();
    for j in 0..k {
        let i = idx[j] as usize;
        assert!(i < points.len(), "index out of range");
        assert_ne!(Some(i), skip, "a point is its own neighbour");
        assert!(seen.insert(i), "index {i} repeated");
        let true_d = dist(points[i], q);
        assert!(
            (f64::from(d[j]) - true_d).abs() <= tol(true_d),
            "distance of {i} wrong"
        );
        assert!(
            (f64::from(d[j]) - truth[j]).abs() <= tol(truth[j]),
            "not the {j}-th nearest"
        );
        if j > 0 {
            assert!(d[j] >= d[j - 1], "not sorted");
        }
    }
}

fn check_self(points: &[[f32; 3]], k: usize) {
    let found = knn(points, Queries::SelfExcluded, k).unwrap();
    assert_eq!(found.len(), points.len());
    for (i, &p) in points.iter().enumerate() {
        check_row(points, p, Some(i), &found, i);
    }
}

#[test]
fn random_self_neighbours_match_brute_force() {
    let mut rng = fastrand::Rng::with_seed(1);
    let points = random_points(&mut rng, 700, 2.0);
    for k in [1, 3, 16, 699] {
        check_self(&points, k);
    }
}

#[test]
fn external_queries_match_brute_force() {
    let mut rng = fastrand::Rng::with_seed(2);
    let points = random_points(&mut rng, 500, 1.0);
    // Queries partly outside the points' box, to exercise pruning from afar.
    let queries: Vec<[f32; 3]> = random_points(&mut rng, 300, 3.0)
        .into_iter()
        .map(|p| p.map(|c| c - 1.0))
        .collect();
    for k in [1, 7, 500] {
        let found = knn(&points, Queries::Points(&queries), k).unwrap();
        assert_eq!(found.len(), queries.len());
        for (i, &q) in queries.iter().enumerate() {
            check_row(&points, q, None, &found, i);
        }
    }
}

#[test]
fn a_kept_tree_answers_small_and_large_query_sets_like_brute_force() {
    // Query sets of one task's size run on the calling thread, larger ones in the pool in
    // Morton order: both must give every row its own neighbours, call after call.
    let mut rng = fastrand::Rng::with_seed(5);
    let points = random_points(&mut rng, 4000, 1.0);
    let tree = NearestTree::new(&points).unwrap();
    assert_eq!(tree.len(), points.len());
    for (count, k) in [(1, 1), (300, 1), (512, 2), (513, 1), (5000, 3)] {
        let queries: Vec<[f32; 3]> = random_points(&mut rng, count, 1.4)
            .into_iter()
            .map(|p| p.map(|c| c - 0.2))
            .collect();
        let found = tree.query(&queries, k).unwrap();
        assert_eq!(found.len(), count);
        for i in (0..count).step_by(7) {
            check_row(&points, queries[i], None, &found, i);
        }
        let once = knn(&points, Queries::Points(&queries), k).unwrap();
        assert_eq!(once.indices, found.indices);
        assert_eq!(once.distances, found.distances);
    }
}

#[test]
fn deep_tree_in_parallel_matches_brute_force_on_a_sample() {
    let mut rng = fastrand::Rng::with_seed(3);
    let points = random_points(&mut rng, 30_000, 1.0);
    let k = 16;
    let found = knn(&points, Queries::SelfExcluded, k).unwrap();
    for i in (0..points.len()).step_by(97) {
        check_row(&points, points[i], Some(i), &found, i);
    }
}

#[test]
fn identical_points_are_all_at_distance_zero() {
    let points = vec![[0.25f32, -1.0, 3.0]; 200];
    for k in [1, 10, 199] {
        let found = knn(&points, Queries::SelfExcluded, k).unwrap();
        assert!(found.distances.iter().all(|&d| d == 0.0));
        check_self(&points, k);
    }
}

#[test]
fn collinear_points_with_tied_distances() {
    // Integer spacing on a line: inner points have two neighbours at exactly equal distance.
    let points: Vec<[f32; 3]> = (0..300).map(|i| [i as f32, 2.0 * i as f32, 0.0]).collect();
    for k in [1, 2, 5, 299] {
        check_self(&points, k);
    }
}

#[test]
fn clusters_of_duplicates_among_random_points() {
    let mut rng = fastrand::Rng::with_seed(4);
    let mut points = random_points(&mut rng, 300, 1.0);
    let copies: Vec<[f32; 3]> = points.iter().take(50).flat_map(|&p| [p, p, p]).collect();
    points.extend(copies);
    check_self(&points, 4);
}

#[test]
fn empty_inputs_give_empty_results() {
    let none: Vec<[f32; 3]> = Vec::new();
    let found = knn(&none, Queries::SelfExcluded, 3).unwrap();
    assert!(found.is_empty() && found.distances.is_empty());
    let points = vec![[0.0f32; 3]; 5];
    let found = knn(&points, Queries::Points(&none), 3).unwrap();
    assert!(found.is_empty());
}

fn message(err: GearError) -> String {
    match err {
        GearError::InvalidInput(m) => m,
        other => panic!("expected InvalidInput, got {other:?}"),
    }
}

#[test]
fn bad_input_is_rejected_with_the_argument_named() {
    let points = vec![[0.0f32, 1.0, 2.0]; 4];
    fn err<T>(r: gear_core::Result<T>) -> String {
        message(r.err().expect("should fail"))
    }
    assert!(err(knn(&points, Queries::SelfExcluded, 0)).starts_with("k:"));
    assert!(err(knn(&points, Queries::SelfExcluded, 4)).starts_with("k:"));
    assert!(knn(&points, Queries::SelfExcluded, 3).is_ok());
    let q = [[0.0f32; 3]];
    assert!(err(knn(&points, Queries::Points(&q), 5)).starts_with("k:"));
    let mut bad = points.clone();
    bad[2][1] = f32::NAN;
    assert!(err(knn(&bad, Queries::SelfExcluded, 1)).starts_with("points: row 2"));
    let inf = [[0.0f32, f32::INFINITY, 0.0]];
    assert!(err(knn(&points, Queries::Points(&inf), 1)).starts_with("queries: row 0"));
    assert!(err(knn(&[], Queries::Points(&q), 1)).starts_with("k:"));
    assert!(err(NearestTree::new(&bad)).starts_with("points: row 2"));
    let tree = NearestTree::new(&points).unwrap();
    assert!(err(tree.query(&q, 0)).starts_with("k:"));
    assert!(err(tree.query(&q, 5)).starts_with("k:"));
    assert!(err(tree.query(&inf, 1)).starts_with("queries: row 0"));
    assert!(tree.query(&[], 2).unwrap().is_empty());
}
