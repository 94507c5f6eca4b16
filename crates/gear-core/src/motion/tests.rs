//! The op against central finite differences of itself in f64, f32 against f64, hard cases
//! (a vanishing mix, opposite quaternion signs, half turns) and the f32 driver (eight
//! Gaussians per SIMD lane, in chunks) against one Gaussian at a time.

use super::*;

/// A named input array of a scene, for the finite-difference loop.
type Field = fn(&mut Scene) -> &mut Vec<f64>;

struct Scene<T = f64> {
    means: Vec<T>,
    quats: Vec<T>,
    weights: Vec<T>,
    qr: Vec<T>,
    qd: Vec<T>,
    /// `weights` are logits (see [`DeformInput::softmax`]).
    softmax: bool,
}

impl<T: Copy> Scene<T> {
    fn input(&self) -> DeformInput<'_, T> {
        DeformInput {
            means: &self.means,
            quats: &self.quats,
            weights: &self.weights,
            qr: &self.qr,
            qd: &self.qd,
            softmax: self.softmax,
            softmax_weights: None,
        }
    }

    /// Every value converted by `f`.
    fn map<U>(&self, f: impl Fn(T) -> U) -> Scene<U> {
        let all = |v: &[T]| v.iter().map(|&x| f(x)).collect();
        Scene {
            means: all(&self.means),
            quats: all(&self.quats),
            weights: all(&self.weights),
            qr: all(&self.qr),
            qd: all(&self.qd),
            softmax: self.softmax,
        }
    }
}

fn uniform(rng: &mut fastrand::Rng, n: usize, lo: f64, hi: f64) -> Vec<f64> {
    (0..n).map(|_| lo + (hi - lo) * rng.f64()).collect()
}

/// Unit dual quaternions of random motions; every other one has its sign flipped (the same
/// motion), so that the blend must align signs.
fn random_motions(rng: &mut fastrand::Rng, k: usize) -> (Vec<f64>, Vec<f64>) {
    let (mut qr, mut qd) = (vec![], vec![]);
    for p in 0..k {
        let r = uniform(rng, 4, -1.0, 1.0);
        let n = r.iter().map(|v| v * v).sum::<f64>().sqrt();
        let sign = if p % 2 == 1 { -1.0 } else { 1.0 };
        let r: [f64; 4] = std::array::from_fn(|i| sign * r[i] / n);
        let t = uniform(rng, 3, -0.5, 0.5);
        let d = quat::mul(&[0.0, t[0], t[1], t[2]], &r);
        qr.extend_from_slice(&r);
        qd.extend(d.iter().map(|v| 0.5 * v));
    }
    (qr, qd)
}

fn random_scene(seed: u64, n: usize, k: usize) -> Scene {
    let mut rng = fastrand::Rng::with_seed(seed);
    let (qr, qd) = random_motions(&mut rng, k);
    Scene {
        means: uniform(&mut rng, 3 * n, -1.0, 1.0),
        quats: uniform(&mut rng, 4 * n, -1.0, 1.0),
        weights: uniform(&mut rng, k * n, 0.0, 1.0),
        qr,
        qd,
        softmax: false,
    }
}

/// [`random_scene`] with logits in [-3, 3] instead of weights.
fn random_logit_scene(seed: u64, n: usize, k: usize) -> Scene {
    let mut rng = fastrand::Rng::with_seed(seed + 1000);
    Scene {
        weights: uniform(&mut rng, k * n, -3.0, 3.0),
        softmax: true,
        ..random_scene(seed, n, k)
    }
}

/// sum(out · probe) for fixed random probes: the scalar whose gradient is checked.
fn loss(scene: &Scene, probe_m: &[f64], probe_q: &[f64]) -> f64 {
    let out = forward(&scene.input()).unwrap();
    quat::dot_slices(&out.means, probe_m) + quat::dot_slices(&out.quats, probe_q)
}

#[test]
fn gradients_match_finite_differences() {
    let cases = [(1, 1), (2, 2), (3, 3), (4, 5)];
    let scenes = cases.iter().flat_map(|&(seed, k)| {
        [
            (seed, k, random_scene(seed, 6, k)),
            (seed, k, random_logit_scene(seed, 6, k)),
        ]
    });
    for (seed, k, mut scene) in scenes {
        let mut rng = fastrand::Rng::with_seed(100 + seed);
        let probe_m = uniform(&mut rng, scene.means.len(), -1.0, 1.0);
        let probe_q = uniform(&mut rng, scene.quats.len(), -1.0, 1.0);
        let g = backward(&scene.input(), &probe_m, &probe_q, true).unwrap();
        let h = 1e-6;
        let fields: [(&str, Field, &Vec<f64>); 5] = [
            ("means", |s| &mut s.means, &g.means),
            ("quats", |s| &mut s.quats, &g.quats),
            ("weights", |s| &mut s.weights, &g.weights),
            ("qr", |s| &mut s.qr, &g.qr),
            ("qd", |s| &mut s.qd, &g.qd),
        ];
        for (name, field, analytic) in fields {
            assert_eq!(analytic.len(), field(&mut scene).len(), "{name}");
            for (i, &grad) in analytic.iter().enumerate() {
                let v = field(&mut scene)[i];
                field(&mut scene)[i] = v + h;
                let up = loss(&scene, &probe_m, &probe_q);
                field(&mut scene)[i] = v - h;
                let down = loss(&scene, &probe_m, &probe_q);
                field(&mut scene)[i] = v;
                let numeric = (up - down) / (2.0 * h);
                assert!(
                    (numeric - grad).abs() <= 1e-6 * (1.0 + numeric.abs()),
                    "seed {seed}, K {k}, softmax {}, {name}[{i}]: analytic {grad} vs numeric {numeric}",
                    scene.softmax
                );
            }
        }
    }
}

/// The backward given the softmax weights the forward returned: the same bits as computing
/// them again; and they are the softmax of the logits. Such weights without `softmax`, or of
/// the wrong length, are refused.
#[test]
fn the_forwards_softmax_weights_serve_the_backward() {
    let scene = random_logit_scene(13, 9000, 4).map(|v| v as f32);
    let out = forward(&scene.input()).unwrap();
    assert_eq!(out.weights.len(), scene.weights.len());
    for (row, logits) in out
        .weights
        .chunks_exact(4)
        .zip(scene.weights.chunks_exact(4))
    {
        let total: f64 = logits.iter().map(|&v| f64::from(v).exp()).sum();
        for (&w, &l) in row.iter().zip(logits) {
            assert!((f64::from(w) - f64::from(l).exp() / total).abs() < 1e-6);
        }
    }
    let mut rng = fastrand::Rng::with_seed(2);
    let gm: Vec<f32> = (0..scene.means.len()).map(|_| rng.f32() - 0.5).collect();
    let gq: Vec<f32> = (0..scene.quats.len()).map(|_| rng.f32() - 0.5).collect();
    let again = backward(&scene.input(), &gm, &gq, true).unwrap();
    let given = DeformInput {
        softmax_weights: Some(&out.weights),
        ..scene.input()
    };
    let reused = backward(&given, &gm, &gq, true).unwrap();
    let bits = |g: &DeformGradients<f32>| -> Vec<u32> {
        [&g.means, &g.quats, &g.weights, &g.qr, &g.qd]
            .iter()
            .flat_map(|v| v.iter().map(|x| x.to_bits()))
            .collect()
    };
    assert_eq!(bits(&reused), bits(&again));
    let without_softmax = DeformInput {
        softmax: false,
        ..given
    };
    let short = DeformInput {
        softmax_weights: Some(&out.weights[1..]),
        ..given
    };
    for bad in [without_softmax, short] {
        let err = backward(&bad, &gm, &gq, true).unwrap_err().to_string();
        assert!(
            err.contains("softmax_weights must come with softmax"),
            "{err}"
        );
    }
    // Without logits there are no weights to hand on.
    let plain = random_scene(13, 10, 2);
    assert!(forward(&plain.input()).unwrap().weights.is_empty());
}

#[test]
fn logits_give_the_deformation_of_their_softmax() {
    let logits = random_logit_scene(11, 50, 3);
    let mut weights = random_logit_scene(11, 50, 3);
    weights.softmax = false;
    for row in weights.weights.chunks_exact_mut(3) {
        let total: f64 = row.iter().map(|v| v.exp()).sum();
        row.iter_mut().for_each(|v| *v = v.exp() / total);
    }
    let (a, b) = (
        forward(&logits.input()).unwrap(),
        forward(&weights.input()).unwrap(),
    );
    for (x, y) in a
        .means
        .iter()
        .chain(&a.quats)
        .zip(b.means.iter().chain(&b.quats))
    {
        assert!((x - y).abs() < 1e-12, "{x} vs {y}");
    }
    // Logits far apart (a weight underflows to 0) stay finite, forward and backward.
    let mut extreme = random_logit_scene(12, 20, 3);
    extreme
        .weights
        .iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v = if i % 2 == 0 { 50.0 } else { -50.0 });
    let narrow = extreme.map(|v| v as f32);
    let out = forward(&narrow.input()).unwrap();
    let ones = vec![1.0f32; narrow.quats.len()];
    let g = backward(&narrow.input(), &ones[..narrow.means.len()], &ones, true).unwrap();
    assert!(out.means.iter().chain(&out.quats).all(|v| v.is_finite()));
    assert!(g
        .weights
        .iter()
        .chain(&g.qr)
        .chain(&g.qd)
        .all(|v| v.is_finite()));
}

#[test]
fn pure_motions_move_rigidly() {
    // One-hot weights: the Gaussian moves exactly by its part's motion, whatever the signs.
    let mut scene = random_scene(7, 4, 3);
    for (i, w) in scene.weights.chunks_exact_mut(3).enumerate() {
        w.fill(0.0);
        w[i % 3] = 1.0;
    }
    let out = forward(&scene.input()).unwrap();
    for i in 0..4 {
        let p = i % 3;
        let r: [f64; 4] = std::array::from_fn(|j| scene.qr[4 * p + j]);
        let d: [f64; 4] = std::array::from_fn(|j| scene.qd[4 * p + j]);
        let t = quat::mul(&d, &quat::conj(&r));
        let m = [
            scene.means[3 * i],
            scene.means[3 * i + 1],
            scene.means[3 * i + 2],
        ];
        let rotated = quat::rotate(&r, &m);
        for j in 0..3 {
            let want = rotated[j] + 2.0 * t[j + 1];
            assert!((out.means[3 * i + j] - want).abs() < 1e-12, "mean {i},{j}");
        }
    }
}

#[test]
fn float32_agrees_with_float64() {
    // The f32 op on rounded inputs against f64 on the same rounded inputs.
    let scene32 = random_scene(11, 500, 4).map(|x| x as f32);
    let rounded = scene32.map(f64::from);
    let input32 = scene32.input();
    let back = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<f64>>();
    let out32 = forward(&input32).unwrap();
    let out64 = forward(&rounded.input()).unwrap();
    for (a, b) in out32.means.iter().zip(&out64.means) {
        assert!((*a as f64 - b).abs() < 2e-6, "mean {a} vs {b}");
    }
    for (a, b) in out32.quats.iter().zip(&out64.quats) {
        assert!((*a as f64 - b).abs() < 2e-6, "quat {a} vs {b}");
    }
    let gm = vec![0.5f32; scene32.means.len()];
    let gq = vec![-0.25f32; scene32.quats.len()];
    let g32 = backward(&input32, &gm, &gq, true).unwrap();
    let g64 = backward(&rounded.input(), &back(&gm), &back(&gq), true).unwrap();
    for (name, a, b) in [
        ("means", &g32.means, &g64.means),
        ("quats", &g32.quats, &g64.quats),
        ("weights", &g32.weights, &g64.weights),
        ("qr", &g32.qr, &g64.qr),
        ("qd", &g32.qd, &g64.qd),
    ] {
        let err = a
            .iter()
            .zip(b)
            .map(|(&x, y)| (x as f64 - y).powi(2))
            .sum::<f64>();
        let norm = b.iter().map(|y| y * y).sum::<f64>();
        assert!(
            err.sqrt() <= 1e-5 * norm.sqrt().max(1e-12),
            "{name}: relative L2 error"
        );
    }
}

#[test]
fn hard_cases_stay_finite() {
    // All weights zero (the mix vanishes: identity rotation), weights of ±50, half turns whose
    // quaternions have w = 0, and opposite signs of one motion in the same blend.
    let half_turn = [0.0, 0.0, 0.0, 1.0];
    let cases: Vec<(Vec<f64>, Vec<f64>, Vec<f64>)> = vec![
        (
            vec![0.0, 0.0],
            [[1.0, 0.0, 0.0, 0.0], half_turn].concat(),
            vec![0.0; 8],
        ),
        (
            vec![50.0, -50.0],
            [half_turn, half_turn].concat(),
            vec![0.1; 8],
        ),
        (
            vec![0.5, 0.5],
            [[0.6, 0.8, 0.0, 0.0], [-0.6, -0.8, 0.0, 0.0]].concat(),
            vec![0.0, 0.3, 0.0, 0.0, 0.0, -0.3, 0.0, 0.0],
        ),
        (
            vec![0.5, 0.5],
            [half_turn, [0.0, 0.0, 0.0, -1.0]].concat(),
            vec![0.0; 8],
        ),
    ];
    for (c, (weights, qr, qd)) in cases.into_iter().enumerate() {
        let scene = Scene {
            means: vec![0.3, -0.2, 0.1],
            quats: vec![0.0, 0.0, 0.0, 0.0],
            weights,
            qr,
            qd,
            softmax: false,
        };
        let out = forward(&scene.input()).unwrap();
        let g = backward(
            &scene.input(),
            &[1.0, -1.0, 0.5],
            &[0.2, 0.1, -0.3, 0.4],
            true,
        )
        .unwrap();
        let all = [
            &out.means, &out.quats, &g.means, &g.quats, &g.weights, &g.qr, &g.qd,
        ];
        for values in all {
            assert!(values.iter().all(|v| v.is_finite()), "case {c}: {values:?}");
        }
        if c == 0 {
            // The vanished mix is the identity rotation: the mean is not turned.
            assert_eq!(&out.means[..], &scene.means[..], "case 0");
        }
    }
}

/// Gaussian `i` of `scene` alone, as a scene of one.
fn alone(scene: &Scene<f32>, i: usize) -> Scene<f32> {
    let k = scene.qr.len() / 4;
    Scene {
        means: scene.means[3 * i..3 * i + 3].to_vec(),
        quats: scene.quats[4 * i..4 * i + 4].to_vec(),
        weights: scene.weights[k * i..k * (i + 1)].to_vec(),
        qr: scene.qr.clone(),
        qd: scene.qd.clone(),
        softmax: scene.softmax,
    }
}

#[test]
fn lanes_match_one_gaussian_at_a_time() {
    // In f32 a chunk runs eight Gaussians per SIMD lane and its last few alone: over several
    // chunks (each with a tail), each Gaussian's outputs and gradients are the bits it gets
    // deformed alone, with weights and with logits, among them Gaussians whose mix vanishes
    // (all weights zero) beside live ones; the motions' gradients are the chunks' sums added
    // in chunk order.
    let k = 3;
    let n = 2 * CHUNK + 17;
    let mut plain = random_scene(21, n, k);
    for (i, row) in plain.weights.chunks_exact_mut(k).enumerate() {
        row.iter_mut()
            .for_each(|w| *w = if i % 5 == 0 { 0.0 } else { w.powi(4) });
    }
    for scene in [
        plain.map(|x| x as f32),
        random_logit_scene(22, n, k).map(|x| x as f32),
    ] {
        let input = scene.input();
        let gm: Vec<f32> = (0..3 * n).map(|i| (i % 7) as f32 - 3.0).collect();
        let gq: Vec<f32> = (0..4 * n).map(|i| (i % 5) as f32 * 0.1).collect();
        let out = forward(&input).unwrap();
        let g = backward(&input, &gm, &gq, true).unwrap();
        for i in 0..n {
            let one = alone(&scene, i);
            let (m, q) = (&gm[3 * i..3 * i + 3], &gq[4 * i..4 * i + 4]);
            let (o, gi) = (
                forward(&one.input()).unwrap(),
                backward(&one.input(), m, q, true).unwrap(),
            );
            let softmax = scene.softmax;
            assert_eq!(
                &out.means[3 * i..3 * i + 3],
                &o.means[..],
                "mean {i} {softmax}"
            );
            assert_eq!(
                &out.quats[4 * i..4 * i + 4],
                &o.quats[..],
                "quat {i} {softmax}"
            );
            if softmax {
                assert_eq!(&out.weights[k * i..k * (i + 1)], &o.weights[..], "w {i}");
            }
            assert_eq!(&g.means[3 * i..3 * i + 3], &gi.means[..], "grad mean {i}");
            assert_eq!(&g.quats[4 * i..4 * i + 4], &gi.quats[..], "grad quat {i}");
            assert_eq!(
                &g.weights[k * i..k * (i + 1)],
                &gi.weights[..],
                "grad w {i}"
            );
        }
        assert_eq!(out.weights.is_empty(), !scene.softmax);
        let (mut qr, mut qd) = (vec![0.0f32; 4 * k], vec![0.0f32; 4 * k]);
        for start in (0..n).step_by(CHUNK) {
            let end = (start + CHUNK).min(n);
            let part = DeformInput {
                means: &input.means[3 * start..3 * end],
                quats: &input.quats[4 * start..4 * end],
                weights: &input.weights[k * start..k * end],
                ..input
            };
            let gp = backward(
                &part,
                &gm[3 * start..3 * end],
                &gq[4 * start..4 * end],
                true,
            );
            let gp = gp.unwrap();
            qr.iter_mut().zip(&gp.qr).for_each(|(t, v)| *t += v);
            qd.iter_mut().zip(&gp.qd).for_each(|(t, v)| *t += v);
        }
        assert_eq!((&g.qr, &g.qd), (&qr, &qd));
        // Held motions: the same gradients for the Gaussians, none for the motions.
        let held = backward(&input, &gm, &gq, false).unwrap();
        assert_eq!((&held.means, &held.weights), (&g.means, &g.weights));
        assert!(held.qr.is_empty() && held.qd.is_empty());
    }
}

#[test]
fn bad_inputs_are_errors() {
    let scene = random_scene(5, 3, 2);
    let mut input = scene.input();
    input.weights = &scene.weights[..5];
    assert!(forward(&input)
        .unwrap_err()
        .to_string()
        .contains("weights must hold 6"));
    let nan = [f64::NAN, 0.0, 0.0];
    let mut means = scene.means.clone();
    means[..3].copy_from_slice(&nan);
    let input = DeformInput {
        means: &means,
        ..scene.input()
    };
    let err = forward(&input).unwrap_err().to_string();
    assert!(
        err.contains("deform means has a non-finite value at flat index 0"),
        "{err}"
    );
    let empty = DeformInput {
        qr: &[],
        qd: &[],
        ..scene.input()
    };
    assert!(forward(&empty).unwrap_err().to_string().contains("K >= 1"));
}
