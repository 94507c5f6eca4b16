//! The CPU executor against the f64 reference (same scenes and hard cases as the GPU's tests in
//! splat/tests.rs), against the GPU kernels, and its determinism: gradients bitwise equal for
//! any thread count and from run to run.

use rayon::ThreadPool;

use super::{backward_in, build_pool, forward_in, CpuState};
use crate::splat::reference;
use crate::splat::tests::{
    all_finite, camera, forward_matches_reference_with, geometry_gradients, gradient_errors,
    gradients_finite, hard_cases_stay_finite_with, needle_scene, options, random_image_grads,
    random_scene, random_scene_sized, relative_l2, saturated_scene, ImageError,
};
use crate::splat::types::{
    Camera, GaussianGradients, OutputGradients, OwnedGaussians, RenderOutput,
};

fn pool(threads: usize) -> ThreadPool {
    build_pool(threads).unwrap()
}

fn render(
    pool: &ThreadPool,
    scene: &OwnedGaussians,
    cam: &Camera,
    depth: bool,
) -> (RenderOutput<f32>, CpuState) {
    forward_in(pool, &scene.view(), cam, &options(scene.channels, depth)).unwrap()
}

/// Worst errors of the feature and alpha images, and of depth, against the reference.
fn forward_errors(scene: &OwnedGaussians, cam: &Camera, depth: bool) -> (ImageError, ImageError) {
    let reference =
        reference::forward(&scene.view(), cam, &options(scene.channels, depth)).unwrap();
    let (out, _) = render(&pool(2), scene, cam, depth);
    let image = ImageError::of(&out.features, &reference.features)
        .worst(ImageError::of(&out.alpha, &reference.alpha));
    let depth_err = match (&out.depth, &reference.depth) {
        (Some(g), Some(r)) => ImageError::of(g, r),
        (None, None) => ImageError::default(),
        _ => panic!("depth present in one output only"),
    };
    (image, depth_err)
}

/// The same scenes and bounds as the GPU's forward_matches_reference.
#[test]
fn forward_matches_reference() {
    forward_matches_reference_with("cpu", forward_errors);
}

fn image_grads(cam: &Camera, channels: usize, seed: u64) -> Vec<Vec<f32>> {
    random_image_grads(cam.pixels(), channels, seed)
}

fn output_grads(img: &[Vec<f32>], depth: bool) -> OutputGradients<'_, f32> {
    OutputGradients {
        features: &img[0][..],
        alpha: &img[1][..],
        depth: depth.then_some(&img[2][..]),
    }
}

/// CPU and reference gradients for the same random image gradients.
fn gradients(
    scene: &OwnedGaussians,
    cam: &Camera,
    depth: bool,
) -> (GaussianGradients<f32>, GaussianGradients<f64>) {
    let pool = pool(2);
    let (_, state) = render(&pool, scene, cam, depth);
    let img = image_grads(cam, scene.channels, 99);
    let cpu = backward_in(&pool, &state, &output_grads(&img, depth), true, 0).unwrap();
    let wide: Vec<Vec<f64>> = img
        .iter()
        .map(|v| v.iter().map(|&x| f64::from(x)).collect())
        .collect();
    let reference = reference::backward(
        &scene.view(),
        cam,
        &options(scene.channels, depth),
        &OutputGradients {
            features: &wide[0][..],
            alpha: &wide[1][..],
            depth: depth.then_some(&wide[2][..]),
        },
    )
    .unwrap();
    (cpu, reference)
}

#[test]
fn gradients_match_reference() {
    let cases = [
        (1usize, 5u64, (90, 70)),
        (1000, 6, (90, 70)),
        (5000, 7, (200, 130)),
    ];
    for (n, seed, (w, h)) in cases {
        let cam = camera(w, h);
        for channels in [3usize, 11] {
            for depth in [false, true] {
                let scene = random_scene(n, channels, seed + channels as u64);
                let (cpu, reference) = gradients(&scene, &cam, depth);
                let errors = gradient_errors(&cpu, &reference);
                eprintln!("cpu gradients n={n} C={channels} depth={depth}: {errors:?}");
                // The GPU suite's bound: at 5000 Gaussians f32 itself is ~1e-4 off (the GPU
                // kernels' errors agree with these to three digits).
                assert!(
                    errors.iter().all(|&e| e < 1e-3),
                    "n={n} C={channels} depth={depth}: {errors:?}"
                );
            }
        }
    }
}

/// Without feature gradients the geometric ones are bit-identical (no atomics, fixed order).
#[test]
fn features_grad_off_keeps_other_gradients() {
    let cam = camera(90, 70);
    let pool = pool(2);
    for channels in [1usize, 5] {
        for depth in [false, true] {
            let scene = random_scene(1000, channels, 40 + channels as u64);
            let (_, state) = render(&pool, &scene, &cam, depth);
            let img = image_grads(&cam, channels, 41);
            let run = |fg| backward_in(&pool, &state, &output_grads(&img, depth), fg, 0).unwrap();
            let (on, off) = (run(true), run(false));
            assert_eq!(on.features.len(), 1000 * channels);
            assert!(off.features.is_empty(), "feature gradients returned");
            let (on, off) = (geometry_gradients(&on), geometry_gradients(&off));
            assert!(
                on.iter().any(|&v| v != 0.0),
                "no geometric gradient to compare"
            );
            assert_eq!(bits(&on), bits(&off), "C={channels} depth={depth}");
        }
    }
}

/// Row g of each of the five gradient arrays, as bits.
fn row_bits(g: &GaussianGradients<f32>, row: usize, channels: usize) -> Vec<u32> {
    let mut v = bits(&g.means[row]);
    v.extend(bits(&g.quats[row]));
    v.extend(bits(&g.log_scales[row]));
    v.push(g.opacity_logits[row].to_bits());
    v.extend(bits(&g.features[row * channels..(row + 1) * channels]));
    v
}

/// Held Gaussians (the first `held`) get zero gradients, the others exactly those of a full
/// backward: the held ones are still replayed for the transmittance the others see.
#[test]
fn held_gaussians_get_zeros_and_the_others_are_unchanged() {
    let cam = camera(90, 70);
    let pool = pool(2);
    let n = 1000;
    for (channels, depth) in [(3usize, true), (4, false)] {
        let scene = random_scene(n, channels, 50 + channels as u64);
        let (_, state) = render(&pool, &scene, &cam, depth);
        let img = image_grads(&cam, channels, 51);
        let run = |held| backward_in(&pool, &state, &output_grads(&img, depth), true, held);
        let full = run(0).unwrap();
        for held in [1, 397, n - 1, n] {
            let part = run(held).unwrap();
            let zeros = vec![0u32; 11 + channels];
            for row in 0..n {
                let got = row_bits(&part, row, channels);
                if row < held {
                    assert_eq!(got, zeros, "held row {row} of {held}: not zero");
                } else {
                    assert_eq!(
                        got,
                        row_bits(&full, row, channels),
                        "row {row}, held {held}"
                    );
                }
            }
        }
        let wanted = (0..n).filter(|&r| row_bits(&full, r, channels).iter().any(|&b| b != 0));
        assert!(wanted.count() > n / 2, "too few gradients to compare");
        let message = run(n + 1)
            .expect_err("more held than Gaussians")
            .to_string();
        assert!(message.contains("held"), "{message}");
    }
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

/// Every output and gradient as bits.
fn all_bits(out: &RenderOutput<f32>, g: &GaussianGradients<f32>) -> Vec<u32> {
    let mut v = bits(&out.features);
    v.extend(bits(&out.alpha));
    v.extend(bits(out.depth.as_deref().unwrap_or(&[])));
    v.extend(bits(&geometry_gradients(g)));
    v.extend(bits(&g.features));
    v
}

/// Images and gradients bitwise equal with 1, 2 and 7 threads, and over two runs.
#[test]
fn deterministic_for_any_thread_count() {
    let cam = camera(200, 130);
    let scene = random_scene(20_000, 3, 77);
    let img = image_grads(&cam, 3, 78);
    let run = |threads| {
        let pool = pool(threads);
        let (out, state) = render(&pool, &scene, &cam, true);
        let g = backward_in(&pool, &state, &output_grads(&img, true), true, 0).unwrap();
        all_bits(&out, &g)
    };
    let first = run(1);
    for threads in [2, 7, 7, 2] {
        assert!(
            first == run(threads),
            "{threads} threads differ from 1 thread"
        );
    }
}

fn widen(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

/// CPU and GPU gradients for the same random image gradients.
fn cpu_and_gpu_gradients(
    scene: &OwnedGaussians,
    cam: &Camera,
    depth: bool,
) -> (GaussianGradients<f32>, GaussianGradients<f32>) {
    use crate::splat::{backward as gpu_backward, forward as gpu_forward, Accumulation};
    let pool = pool(2);
    let (_, gpu_state) = gpu_forward(&scene.view(), cam, &options(scene.channels, depth)).unwrap();
    let (_, cpu_state) = render(&pool, scene, cam, depth);
    let img = image_grads(cam, scene.channels, 5);
    let grads = output_grads(&img, depth);
    let gpu = gpu_backward(&gpu_state, &grads, Accumulation::Auto, true, 0).unwrap();
    let cpu = backward_in(&pool, &cpu_state, &grads, true, 0).unwrap();
    (cpu, gpu)
}

/// The CPU executor and the GPU kernels agree as each agrees with the reference.
#[test]
fn cpu_matches_gpu() {
    use crate::splat::{backward as gpu_backward, forward as gpu_forward, Accumulation};
    let pool = pool(2);
    for (n, seed, (w, h)) in [(3000usize, 51u64, (128, 96)), (20_000, 52, (160, 160))] {
        let cam = camera(w, h);
        for (channels, depth) in [(3usize, true), (11, false)] {
            let scene = random_scene_sized(n, channels, seed, -4.5);
            let opts = options(channels, depth);
            let (gpu_out, gpu_state) = gpu_forward(&scene.view(), &cam, &opts).unwrap();
            let (cpu_out, cpu_state) = render(&pool, &scene, &cam, depth);
            let wide = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<f64>>();
            let image = ImageError::of(&cpu_out.features, &wide(&gpu_out.features))
                .worst(ImageError::of(&cpu_out.alpha, &wide(&gpu_out.alpha)));
            let img = image_grads(&cam, channels, seed);
            let grads = output_grads(&img, depth);
            let gpu = gpu_backward(&gpu_state, &grads, Accumulation::Auto, true, 0).unwrap();
            let cpu = backward_in(&pool, &cpu_state, &grads, true, 0).unwrap();
            let rel = relative_l2(&geometry_gradients(&cpu), &wide(&geometry_gradients(&gpu)));
            let rel_f = relative_l2(&cpu.features, &wide(&gpu.features));
            eprintln!("cpu vs gpu n={n} C={channels}: image {image:?}, grads {rel:e} {rel_f:e}");
            assert!(image.max <= 1e-4, "n={n}: image {image:?}");
            assert!(
                rel < 1e-4 && rel_f < 1e-4,
                "n={n}: gradients {rel:e} {rel_f:e}"
            );
        }
    }
}

/// Forward and backward finite everywhere (outputs start as NaN, so every pixel must be
/// written); forward within the reference's bounds when `compare`.
fn check_finite(
    name: &str,
    scene: &OwnedGaussians,
    cam: &Camera,
    compare: bool,
) -> GaussianGradients<f32> {
    let pool = pool(3);
    let (out, state) = render(&pool, scene, cam, true);
    let depth = out.depth.as_ref().unwrap();
    assert!(
        all_finite(&out.features) && all_finite(&out.alpha) && all_finite(depth),
        "{name}: non-finite forward output"
    );
    if compare {
        let reference =
            reference::forward(&scene.view(), cam, &options(scene.channels, true)).unwrap();
        let err = ImageError::of(&out.features, &reference.features)
            .worst(ImageError::of(&out.alpha, &reference.alpha));
        assert!(
            err.within_flips(),
            "{name}: forward differs from reference {err:?}"
        );
    }
    let img = image_grads(cam, scene.channels, 7);
    let g = backward_in(&pool, &state, &output_grads(&img, true), true, 0).unwrap();
    assert!(gradients_finite(&g), "{name}: non-finite gradient");
    g
}

/// The hard cases of the GPU suite, on the CPU executor.
#[test]
fn hard_cases_stay_finite() {
    hard_cases_stay_finite_with(check_finite);
}

/// Needles at random angles: the row test must not drop a pixel the ellipse reaches.
#[test]
fn needles_match_reference() {
    let scene = needle_scene();
    for depth in [false, true] {
        let (image, depth_err) = forward_errors(&scene, &camera(90, 70), depth);
        for (what, e) in [("image", image), ("depth", depth_err)] {
            assert!(e.max <= 1e-4, "depth={depth}: {what} error {e:?}");
        }
        // f32 itself is ~1e-3 off the f64 gradients of needles (the GPU's too), and the two
        // f32 executors differ by ~2e-4 (sums in another order): bound the agreement at 1e-3.
        let (cpu, gpu) = cpu_and_gpu_gradients(&scene, &camera(90, 70), depth);
        let rel = relative_l2(&geometry_gradients(&cpu), &widen(&geometry_gradients(&gpu)));
        assert!(rel < 1e-3, "needles: cpu vs gpu gradients {rel:e}");
    }
}

/// Large opaque Gaussians: rows stop early, and the backward replays each row's own prefix.
#[test]
fn saturated_scene_matches_reference() {
    let scene = saturated_scene();
    let cam = camera(90, 70);
    let (image, depth_err) = forward_errors(&scene, &cam, true);
    for (what, e) in [("image", image), ("depth", depth_err)] {
        assert!(e.max <= 1e-4, "{what} error {e:?}");
    }
    let (cpu, reference) = gradients(&scene, &cam, true);
    let errors = gradient_errors(&cpu, &reference);
    eprintln!("cpu saturated gradients: {errors:?}");
    assert!(errors.iter().all(|&e| e < 1e-3), "{errors:?}");
}

/// Row culling skips work: on small splats far fewer evaluations than tile pixels x pairs,
/// and every contribution is one of them.
#[test]
fn row_test_skips_most_evaluations() {
    let cam = camera(128, 128);
    let scene = random_scene_sized(20_000, 3, 61, -5.5);
    let (_, state) = render(&pool(2), &scene, &cam, false);
    let s = state.stats;
    eprintln!("{s:?}");
    assert!(s.contributions > 0 && s.contributions <= s.evaluations);
    assert!(s.evaluations * 2 < s.pairs * 64, "{s:?}");
}

/// The backward skips the rows where the forward blended an entry into no pixel: the same
/// gradients, bit for bit, as replaying every row the entry's ellipse spans. Also checks that
/// the skip skips something on a scene of sub-pixel splats (else it would test nothing).
#[test]
fn skipping_unblended_rows_changes_no_gradient() {
    let cam = camera(120, 90);
    let pool = pool(2);
    for (n, seed) in [(3000usize, 5u64), (20_000, 6)] {
        let scene = random_scene(n, 3, seed);
        let (_, mut state) = render(&pool, &scene, &cam, true);
        let img = image_grads(&cam, 3, seed + 1);
        let grads = |state: &CpuState| {
            let g = backward_in(&pool, state, &output_grads(&img, true), true, 0).unwrap();
            let mut v = bits(&geometry_gradients(&g));
            v.extend(bits(&g.features));
            v
        };
        let skipping = grads(&state);
        let spanned: Vec<u8> = state.bins.entries.iter().map(|e| e.rows as u8).collect();
        let skipped = spanned
            .iter()
            .zip(&state.pixels.blended_rows)
            .filter(|(s, b)| s != b)
            .count();
        assert!(skipped > 0, "N={n}: every spanned row was blended");
        state.pixels.blended_rows = spanned;
        assert!(
            skipping == grads(&state),
            "N={n}: the skip changed a gradient"
        );
    }
}

/// `scene` reordered so that the Gaussians right of x = `cut` come last; returns how many
/// come first.
fn left_first(scene: &OwnedGaussians, cut: f32) -> (OwnedGaussians, usize) {
    let c = scene.channels;
    let mut order: Vec<usize> = (0..scene.means.len()).collect();
    order.sort_by_key(|&g| scene.means[g][0] > cut);
    let mut out = OwnedGaussians::new(c);
    for &g in &order {
        out.push(
            scene.means[g],
            scene.quats[g],
            scene.log_scales[g],
            scene.opacity_logits[g],
            &scene.features[g * c..(g + 1) * c],
        );
    }
    let left = order.iter().filter(|&&g| scene.means[g][0] <= cut).count();
    (out, left)
}

/// A render over a static layer of the first `split` Gaussians gives the full forward's
/// images bit for bit, and its backward (those Gaussians held) the full backward's gradients,
/// on any thread count; with the moving Gaussians on one side of the image it blends fewer
/// pixels (the other tiles are the layer's).
#[test]
fn render_over_a_static_layer_is_a_full_render() {
    use super::{forward_over_in, StaticLayer};
    let cam = camera(120, 90);
    for (n, channels, depth, seed) in [(4000usize, 3usize, true, 81u64), (20_000, 4, false, 82)] {
        let (scene, left) = left_first(&random_scene(n, channels, seed), 0.6);
        let img = image_grads(&cam, channels, seed + 1);
        let mut background = options(channels, depth);
        background.background.iter_mut().for_each(|b| *b = 0.7 - *b);
        for split in [0, 1, 1237, left, n - 1, n] {
            let (full, full_state) =
                forward_in(&pool(2), &scene.view(), &cam, &background).unwrap();
            let full_grads = backward_in(
                &pool(2),
                &full_state,
                &output_grads(&img, depth),
                true,
                split,
            )
            .unwrap();
            let expected = all_bits(&full, &full_grads);
            let static_part = OwnedGaussians {
                means: scene.means[..split].to_vec(),
                quats: scene.quats[..split].to_vec(),
                log_scales: scene.log_scales[..split].to_vec(),
                opacity_logits: scene.opacity_logits[..split].to_vec(),
                features: scene.features[..split * channels].to_vec(),
                channels,
            };
            for threads in [1, 2, 7] {
                let pool = pool(threads);
                let layer = StaticLayer::new_in(&pool, &static_part.view(), &cam, depth).unwrap();
                let (out, state) =
                    forward_over_in(&pool, &layer, &scene.view(), &cam, &background).unwrap();
                let grads =
                    backward_in(&pool, &state, &output_grads(&img, depth), true, split).unwrap();
                assert!(
                    all_bits(&out, &grads) == expected,
                    "n={n} split={split} threads={threads}: differs from the full render"
                );
                if split == left {
                    let (saved, all) = (state.stats.evaluations, full_state.stats.evaluations);
                    assert!(3 * saved < 2 * all, "n={n}: {saved} of {all} evaluations");
                }
            }
        }
    }
}

/// A render over a layer refuses other Gaussians in the layer's place, another channel count
/// or depth setting, and a backward that asks gradients of the layer's Gaussians.
#[test]
fn render_over_a_static_layer_checks_its_inputs() {
    use super::{forward_over_in, StaticLayer};
    let (cam, pool) = (camera(60, 40), pool(2));
    let scene = random_scene(500, 3, 90);
    let first = OwnedGaussians {
        means: scene.means[..200].to_vec(),
        quats: scene.quats[..200].to_vec(),
        log_scales: scene.log_scales[..200].to_vec(),
        opacity_logits: scene.opacity_logits[..200].to_vec(),
        features: scene.features[..600].to_vec(),
        channels: 3,
    };
    let layer = StaticLayer::new_in(&pool, &first.view(), &cam, true).unwrap();
    assert_eq!(
        (layer.len(), layer.channels(), layer.depth()),
        (200, 3, true)
    );
    let error = |scene: &OwnedGaussians, depth: bool| {
        forward_over_in(
            &pool,
            &layer,
            &scene.view(),
            &cam,
            &options(scene.channels, depth),
        )
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default()
    };
    let mut moved = scene.clone();
    moved.opacity_logits[199] += 1e-6;
    assert!(
        error(&moved, true).contains("not the layer's"),
        "{}",
        error(&moved, true)
    );
    assert!(
        error(&scene, false).contains("depth"),
        "{}",
        error(&scene, false)
    );
    assert!(error(&random_scene(500, 4, 90), true).contains("channels"));
    assert!(error(&first, true).is_empty(), "the layer alone renders");
    let mut fewer = first.clone();
    fewer.means.pop();
    fewer.quats.pop();
    fewer.log_scales.pop();
    fewer.opacity_logits.pop();
    fewer.features.truncate(597);
    assert!(error(&fewer, true).contains("not the layer's"));
    let other = camera(60, 41);
    let message = forward_over_in(&pool, &layer, &scene.view(), &other, &options(3, true))
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(message.contains("another camera"), "{message}");
    let (out, state) =
        forward_over_in(&pool, &layer, &scene.view(), &cam, &options(3, true)).unwrap();
    let img = image_grads(&cam, 3, 91);
    let message = backward_in(&pool, &state, &output_grads(&img, true), true, 199)
        .expect_err("gradients of a layer Gaussian")
        .to_string();
    assert!(message.contains("static layer"), "{message}");
    assert!(all_finite(&out.features));
}
