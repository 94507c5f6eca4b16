//! GPU rasterizer against the f64 reference (`super::reference`): forward images and
//! gradients on random scenes, and hard cases that must stay finite. Outputs are poisoned
//! with NaN before the kernels run, so an unwritten pixel or gradient fails.

use super::backward::{backward_impl, Accumulation};
use super::forward::{forward_impl, ForwardRun};
use super::reference;
use super::test_rng::Rng;
use super::types::{Camera, GaussianGradients, OutputGradients, OwnedGaussians, RenderOptions};
use crate::gpu::GpuContext;

/// `n` Gaussians spread through the view of [`camera`], of a few pixels to a few tiles.
pub(crate) fn random_scene(n: usize, channels: usize, seed: u64) -> OwnedGaussians {
    random_scene_sized(n, channels, seed, -4.0)
}

/// As [`random_scene`] with log-scales around `log_scale`.
pub(crate) fn random_scene_sized(
    n: usize,
    channels: usize,
    seed: u64,
    log_scale: f32,
) -> OwnedGaussians {
    let mut rng = Rng(seed);
    let mut s = OwnedGaussians::new(channels);
    for _ in 0..n {
        s.means.push([
            rng.uniform(-1.6, 1.6),
            rng.uniform(-1.3, 1.3),
            rng.uniform(-1.5, 1.5),
        ]);
        s.quats.push([
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        ]);
        let base = log_scale + rng.uniform(0.0, 1.8);
        s.log_scales.push([
            base + rng.uniform(-0.5, 0.5),
            base + rng.uniform(-0.5, 0.5),
            base + rng.uniform(-0.5, 0.5),
        ]);
        s.opacity_logits.push(rng.uniform(-3.0, 3.0));
        for _ in 0..channels {
            s.features.push(rng.uniform(-0.2, 1.0));
        }
    }
    s
}

/// Isotropic Gaussians from rows of (mean, quaternion, log-scale, opacity logit), each with
/// features 0.25, 0.35, ...
pub(crate) fn plain_scene(
    channels: usize,
    rows: &[([f32; 3], [f32; 4], f32, f32)],
) -> OwnedGaussians {
    let features: Vec<f32> = (0..channels).map(|c| 0.25 + 0.1 * c as f32).collect();
    let mut s = OwnedGaussians::new(channels);
    for &(mean, quat, log_scale, logit) in rows {
        s.push(mean, quat, [log_scale; 3], logit, &features);
    }
    s
}

/// A camera 4 units from the origin, slightly rotated about y so W_rot is not the identity.
pub(crate) fn camera(width: u32, height: u32) -> Camera {
    let (s, c) = 0.2f32.sin_cos();
    Camera {
        world_to_cam: [
            [c, 0.0, s, 0.1],
            [0.0, 1.0, 0.0, -0.05],
            [-s, 0.0, c, 4.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
        fx: 0.9 * width as f32,
        fy: 0.9 * width as f32,
        cx: 0.5 * width as f32,
        cy: 0.5 * height as f32,
        width,
        height,
    }
}

pub(crate) fn options(channels: usize, depth: bool) -> RenderOptions {
    RenderOptions {
        depth,
        background: (0..channels).map(|c| 0.1 + 0.05 * c as f32).collect(),
    }
}

pub(crate) fn max_abs_diff(gpu: &[f32], reference: &[f64]) -> f64 {
    assert_eq!(gpu.len(), reference.len());
    gpu.iter()
        .zip(reference)
        .map(|(&g, &r)| (f64::from(g) - r).abs())
        .fold(
            0.0,
            |m, d| if d.is_nan() { f64::INFINITY } else { m.max(d) },
        )
}

/// ‖gpu - reference‖ / max(‖reference‖, floor).
pub(crate) fn relative_l2(gpu: &[f32], reference: &[f64]) -> f64 {
    assert_eq!(gpu.len(), reference.len());
    let (mut diff, mut norm) = (0.0, 0.0);
    for (&g, &r) in gpu.iter().zip(reference) {
        diff += (f64::from(g) - r).powi(2);
        norm += r * r;
    }
    let rel = diff.sqrt() / norm.sqrt().max(1e-12);
    if rel.is_nan() {
        f64::INFINITY
    } else {
        rel
    }
}

pub(crate) fn random_image_grads(pixels: usize, channels: usize, seed: u64) -> Vec<Vec<f32>> {
    let mut rng = Rng(seed);
    [pixels * channels, pixels, pixels]
        .iter()
        .map(|&len| (0..len).map(|_| rng.uniform(-1.0, 1.0)).collect())
        .collect()
}

pub(crate) fn all_finite(values: &[f32]) -> bool {
    values.iter().all(|v| v.is_finite())
}

pub(crate) fn gradients_finite(g: &GaussianGradients<f32>) -> bool {
    all_finite(bytemuck::cast_slice(&g.means))
        && all_finite(bytemuck::cast_slice(&g.quats))
        && all_finite(bytemuck::cast_slice(&g.log_scales))
        && all_finite(&g.opacity_logits)
        && all_finite(&g.features)
}

/// Max abs error and the fraction of values off by more than 1e-4.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct ImageError {
    pub max: f64,
    pub over: f64,
}

impl ImageError {
    pub fn of(gpu: &[f32], reference: &[f64]) -> Self {
        let over = gpu
            .iter()
            .zip(reference)
            .filter(|(&g, &r)| {
                (f64::from(g) - r).abs().partial_cmp(&1e-4) != Some(std::cmp::Ordering::Less)
            })
            .count();
        ImageError {
            max: max_abs_diff(gpu, reference),
            over: over as f64 / gpu.len().max(1) as f64,
        }
    }

    /// Within 1e-4 except for rare discrete f32/f64 disagreements (see forward_matches_reference).
    pub fn within_flips(self) -> bool {
        self.max <= 5e-3 && self.over <= 2e-4
    }

    pub fn worst(self, other: Self) -> Self {
        ImageError {
            max: self.max.max(other.max),
            over: self.over.max(other.over),
        }
    }
}

/// Whether the kernels run without subgroup operations, and with them where the adapter has
/// them.
fn subgroup_choices() -> Vec<bool> {
    if GpuContext::global().unwrap().info.features.subgroups {
        vec![false, true]
    } else {
        vec![false]
    }
}

/// GPU forward (every blend path) vs reference: worst errors of the feature and alpha images,
/// and of depth.
fn forward_errors(scene: &OwnedGaussians, cam: &Camera, depth: bool) -> (ImageError, ImageError) {
    let opts = options(scene.channels, depth);
    let reference = reference::forward(&scene.view(), cam, &opts).unwrap();
    let (mut image, mut depth_err) = (ImageError::default(), ImageError::default());
    for subgroups in subgroup_choices() {
        let (gpu, _) =
            forward_impl(&scene.view(), cam, &opts, ForwardRun::checked(subgroups)).unwrap();
        image = image
            .worst(ImageError::of(&gpu.features, &reference.features))
            .worst(ImageError::of(&gpu.alpha, &reference.alpha));
        depth_err = depth_err.worst(match (&gpu.depth, &reference.depth) {
            (Some(g), Some(r)) => ImageError::of(g, r),
            (None, None) => ImageError::default(),
            _ => panic!("depth present in one output only"),
        });
    }
    (image, depth_err)
}

/// Every value within 1e-4 of the f64 reference on scenes of up to 1000 Gaussians. At 50k,
/// f32 and f64 disagree on a handful of discrete decisions (an alpha at exactly 1/255, two
/// depths closer than f32 resolves): there at most 1 value in 5000 may exceed 1e-4, and none
/// 5e-3.
pub(crate) fn forward_matches_reference_with(
    label: &str,
    forward_errors: impl Fn(&OwnedGaussians, &Camera, bool) -> (ImageError, ImageError),
) {
    // The 50k scene gets a larger image and smaller Gaussians (fewer overlaps per pixel).
    let cases = [
        (1usize, 1u64, (90, 70), -4.0),
        (16, 2, (90, 70), -4.0),
        (1000, 3, (90, 70), -4.0),
        (50_000, 4, (300, 200), -5.5),
    ];
    for (n, seed, (w, h), log_scale) in cases {
        let cam = camera(w, h);
        for channels in [3usize, 11] {
            for depth in [false, true] {
                let scene = random_scene_sized(n, channels, seed + channels as u64, log_scale);
                let (image, depth_err) = forward_errors(&scene, &cam, depth);
                eprintln!(
                    "{label} forward n={n} C={channels} depth={depth}: image {image:?} depth {depth_err:?}"
                );
                for (what, e) in [("image", image), ("depth", depth_err)] {
                    let ok = if n <= 1000 {
                        e.max <= 1e-4
                    } else {
                        e.within_flips()
                    };
                    assert!(ok, "n={n} C={channels} depth={depth}: {what} error {e:?}");
                }
            }
        }
    }
}

#[test]
fn forward_matches_reference() {
    forward_matches_reference_with("gpu", forward_errors);
}

/// GPU and reference gradients for the same random image gradients.
fn gradients(
    scene: &OwnedGaussians,
    cam: &Camera,
    depth: bool,
    path: BackwardPath,
) -> (GaussianGradients<f32>, GaussianGradients<f64>) {
    let opts = options(scene.channels, depth);
    let (_, state) = forward_impl(
        &scene.view(),
        cam,
        &opts,
        ForwardRun::checked(path.subgroups),
    )
    .unwrap();
    let img = random_image_grads(cam.pixels(), scene.channels, 99);
    let grads = OutputGradients {
        features: &img[0][..],
        alpha: &img[1][..],
        depth: depth.then_some(&img[2][..]),
    };
    let gpu = backward_impl(
        &state,
        &grads,
        path.accumulation,
        true,
        path.subgroups,
        true,
    )
    .unwrap();
    let wide: Vec<Vec<f64>> = img
        .iter()
        .map(|v| v.iter().map(|&x| f64::from(x)).collect())
        .collect();
    let reference = reference::backward(
        &scene.view(),
        cam,
        &opts,
        &OutputGradients {
            features: &wide[0][..],
            alpha: &wide[1][..],
            depth: depth.then_some(&wide[2][..]),
        },
    )
    .unwrap();
    (gpu, reference)
}

/// Relative L2 error of each gradient array (means, quats, log_scales, opacity, features).
pub(crate) fn gradient_errors(
    gpu: &GaussianGradients<f32>,
    r: &GaussianGradients<f64>,
) -> [f64; 5] {
    [
        relative_l2(
            bytemuck::cast_slice(&gpu.means),
            bytemuck::cast_slice(&r.means),
        ),
        relative_l2(
            bytemuck::cast_slice(&gpu.quats),
            bytemuck::cast_slice(&r.quats),
        ),
        relative_l2(
            bytemuck::cast_slice(&gpu.log_scales),
            bytemuck::cast_slice(&r.log_scales),
        ),
        relative_l2(&gpu.opacity_logits, &r.opacity_logits),
        relative_l2(&gpu.features, &r.features),
    ]
}

/// How the kernels run: blend-backward's native f32 atomics or CAS, and both blends with or
/// without subgroup operations.
#[derive(Debug, Clone, Copy)]
struct BackwardPath {
    accumulation: Accumulation,
    subgroups: bool,
}

/// Every path the adapter can run: CAS always, native f32 atomics where the adapter has them,
/// each with and (where the adapter has subgroups) without subgroup sums.
fn backward_paths() -> Vec<BackwardPath> {
    let mut accumulations = vec![Accumulation::CompareAndSwap];
    if GpuContext::global().unwrap().info.features.float32_atomics {
        accumulations.push(Accumulation::Auto);
    }
    let mut paths = Vec::new();
    for accumulation in accumulations {
        for subgroups in subgroup_choices() {
            paths.push(BackwardPath {
                accumulation,
                subgroups,
            });
        }
    }
    paths
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
                for path in backward_paths() {
                    let scene = random_scene(n, channels, seed + channels as u64);
                    let (gpu, reference) = gradients(&scene, &cam, depth, path);
                    let errors = gradient_errors(&gpu, &reference);
                    eprintln!("gradients n={n} C={channels} depth={depth} {path:?}: {errors:?}");
                    assert!(
                        errors.iter().all(|&e| e < 1e-3),
                        "n={n} C={channels} depth={depth} {path:?}: {errors:?}"
                    );
                }
            }
        }
    }
}

/// The geometric gradients (means, quats, log_scales, opacity) as one flat array.
pub(crate) fn geometry_gradients(g: &GaussianGradients<f32>) -> Vec<f32> {
    let mut flat: Vec<f32> = bytemuck::cast_slice(&g.means).to_vec();
    flat.extend_from_slice(bytemuck::cast_slice(&g.quats));
    flat.extend_from_slice(bytemuck::cast_slice(&g.log_scales));
    flat.extend_from_slice(&g.opacity_logits);
    flat
}

/// Skipping the feature gradients leaves the others as they were: every geometric gradient
/// within 1e-6 of the full backward's (relative to the largest; the atomics add in no fixed
/// order, so bit equality is not promised) on every path, and no feature gradients come back.
#[test]
fn features_grad_off_keeps_other_gradients() {
    let cam = camera(90, 70);
    for channels in [1usize, 5] {
        for depth in [false, true] {
            let scene = random_scene(1000, channels, 40 + channels as u64);
            let opts = options(channels, depth);
            let img = random_image_grads(cam.pixels(), channels, 41);
            let grads = OutputGradients {
                features: &img[0][..],
                alpha: &img[1][..],
                depth: depth.then_some(&img[2][..]),
            };
            for path in backward_paths() {
                let (_, state) = forward_impl(
                    &scene.view(),
                    &cam,
                    &opts,
                    ForwardRun::checked(path.subgroups),
                )
                .unwrap();
                let run = |features_grad| {
                    let accumulation = path.accumulation;
                    backward_impl(
                        &state,
                        &grads,
                        accumulation,
                        features_grad,
                        path.subgroups,
                        true,
                    )
                    .unwrap()
                };
                let (on, off) = (run(true), run(false));
                let case = format!("C={channels} depth={depth} {path:?}");
                assert_eq!(on.features.len(), 1000 * channels, "{case}");
                assert!(
                    off.features.is_empty(),
                    "{case}: feature gradients returned"
                );
                let (on, off) = (geometry_gradients(&on), geometry_gradients(&off));
                assert!(all_finite(&off), "{case}: non-finite gradient");
                let scale = on.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                assert!(scale > 0.0, "{case}: no geometric gradient to compare");
                let wide: Vec<f64> = on.iter().map(|&v| f64::from(v)).collect();
                let diff = max_abs_diff(&off, &wide);
                eprintln!("features_grad off vs on {case}: max diff {diff:e} of {scale:e}");
                assert!(
                    diff <= 1e-6 * f64::from(scale),
                    "{case}: {diff:e} of {scale:e}"
                );
            }
        }
    }
}

/// A camera at the origin looking down +z (world = camera space), for placing hard cases.
pub(crate) fn origin_camera(width: u32, height: u32) -> Camera {
    Camera {
        world_to_cam: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
        fx: width as f32,
        fy: width as f32,
        cx: 0.5 * width as f32,
        cy: 0.5 * height as f32,
        width,
        height,
    }
}

/// Forward and backward (every path) finite everywhere; forward within 1e-4 of the reference
/// (up to rare discrete flips) when `compare` (not for scenes placed exactly on a cull
/// boundary, where f32 and f64 may decide differently); returns the gradients of the last path.
fn check_finite(
    name: &str,
    scene: &OwnedGaussians,
    cam: &Camera,
    compare: bool,
) -> GaussianGradients<f32> {
    let opts = options(scene.channels, true);
    let reference = compare.then(|| reference::forward(&scene.view(), cam, &opts).unwrap());
    let img = random_image_grads(cam.pixels(), scene.channels, 7);
    let grads = OutputGradients {
        features: &img[0][..],
        alpha: &img[1][..],
        depth: Some(&img[2][..]),
    };
    let mut last = None;
    for path in backward_paths() {
        let (out, state) = forward_impl(
            &scene.view(),
            cam,
            &opts,
            ForwardRun::checked(path.subgroups),
        )
        .unwrap();
        let depth = out.depth.as_ref().unwrap();
        assert!(
            all_finite(&out.features) && all_finite(&out.alpha) && all_finite(depth),
            "{name} {path:?}: non-finite forward output"
        );
        if let Some(reference) = &reference {
            let err = ImageError::of(&out.features, &reference.features)
                .worst(ImageError::of(&out.alpha, &reference.alpha));
            assert!(
                err.within_flips(),
                "{name} {path:?}: forward differs from reference {err:?}"
            );
        }
        let g = backward_impl(
            &state,
            &grads,
            path.accumulation,
            true,
            path.subgroups,
            true,
        )
        .unwrap();
        assert!(gradients_finite(&g), "{name} {path:?}: non-finite gradient");
        last = Some(g);
    }
    last.unwrap()
}

/// Renders the field's hard cases through `check` (forward and backward finite, forward
/// against the reference where the case allows a comparison; gradients returned) and asserts
/// what each case implies of the gradients. Shared by the GPU and the CPU executor's tests.
pub(crate) fn hard_cases_stay_finite_with(
    check_finite: impl Fn(&str, &OwnedGaussians, &Camera, bool) -> GaussianGradients<f32>,
) {
    let cam = origin_camera(40, 30);
    let id = [1.0, 0.0, 0.0, 0.0];

    let near = plain_scene(
        3,
        &[
            ([0.0, 0.0, 0.01], id, -3.0, 2.0), // exactly at the near plane
            ([0.001, 0.0, 0.010_001], id, -5.0, 2.0), // just inside
            ([0.0, 0.0, -1.0], id, -1.0, 2.0), // behind the camera
            ([0.0, 0.0, 0.009], id, -1.0, 2.0), // just too near
            ([0.1, 0.0, 2.0], id, -3.0, 0.0),  // an ordinary one
        ],
    );
    let g = check_finite("near plane", &near, &cam, false);
    for culled in [2, 3] {
        assert_eq!(
            g.means[culled], [0.0; 3],
            "culled Gaussian {culled} got a gradient"
        );
        assert_eq!(g.opacity_logits[culled], 0.0);
    }

    let mut non_finite = random_scene(40, 3, 21);
    non_finite.means[3][1] = f32::NAN;
    non_finite.quats[5][0] = f32::INFINITY;
    non_finite.log_scales[7][2] = f32::NEG_INFINITY;
    non_finite.features[8 * 3] = f32::NAN;
    // exp overflows f32 (culled here, not by the f64 reference: no reference comparison).
    non_finite.log_scales[10] = [100.0; 3];
    let g = check_finite("non-finite inputs", &non_finite, &camera(40, 30), false);
    for culled in [3, 5, 7, 8, 10] {
        assert_eq!(
            g.means[culled], [0.0; 3],
            "culled Gaussian {culled} got a gradient"
        );
        assert_eq!(g.features[3 * culled..3 * culled + 3], [0.0; 3]);
    }

    let scales = plain_scene(
        3,
        &[
            ([0.0, 0.0, 2.0], [0.3, 0.1, 0.2, 0.9], 1e-7f32.ln(), 1.0),
            ([0.05, 0.0, 2.0], [0.3, 0.1, 0.2, 0.9], 1e3f32.ln(), 1.0),
            ([0.0, 0.05, 0.02], [0.7, 0.1, 0.2, 0.1], 1e3f32.ln(), 1.0),
        ],
    );
    check_finite("extreme scales", &scales, &cam, true);

    let quats = plain_scene(
        3,
        &[
            ([0.0, 0.0, 2.0], [0.0; 4], -2.5, 1.0),
            ([0.02, 0.0, 2.0], [1e-30, 0.0, 0.0, 0.0], -2.5, 1.0),
        ],
    );
    let g = check_finite("zero quaternion", &quats, &cam, true);
    assert_eq!(
        g.quats[0], [0.0; 4],
        "a zero quaternion must get zero gradient"
    );
    assert!(
        g.means[0].iter().any(|&v| v != 0.0),
        "the Gaussian itself still learns"
    );

    let logits = plain_scene(
        11,
        &[
            ([0.0, 0.0, 2.0], id, -2.5, 50.0),
            ([0.01, 0.0, 2.5], id, -2.5, -50.0),
            ([0.0, 0.01, 3.0], id, -2.5, 50.0),
        ],
    );
    check_finite("opacity logits +-50", &logits, &cam, true);

    let stacked: Vec<_> = (0..10_000)
        .map(|k| ([0.0, 0.0, 2.0 + k as f32 * 1e-3], id, -4.0, 0.5))
        .collect();
    check_finite(
        "10k stacked on one pixel",
        &plain_scene(3, &stacked),
        &cam,
        true,
    );

    let mut off = random_scene(500, 3, 11);
    for m in &mut off.means {
        m[0] += 100.0;
    }
    let g = check_finite("all off-screen", &off, &cam, true);
    assert!(g.features.iter().all(|&v| v == 0.0));

    check_finite("no Gaussians", &OwnedGaussians::new(3), &cam, true);
    check_finite("1x1 image", &random_scene(200, 3, 12), &camera(1, 1), true);
    check_finite(
        "1000x700 image",
        &random_scene(3000, 3, 13),
        &camera(1000, 700),
        true,
    );
    check_finite(
        "odd 37x23 image",
        &random_scene(500, 3, 14),
        &camera(37, 23),
        true,
    );
}

#[test]
fn hard_cases_stay_finite() {
    hard_cases_stay_finite_with(check_finite);
}

/// 300 needles (one axis ~30x the others) at random angles, fairly opaque.
pub(crate) fn needle_scene() -> OwnedGaussians {
    let mut scene = random_scene_sized(300, 3, 31, -3.5);
    for s in &mut scene.log_scales {
        *s = [s[0] + 1.7, s[1] - 1.7, s[2] - 1.7];
    }
    for l in &mut scene.opacity_logits {
        *l += 2.0;
    }
    scene
}

/// 600 large, nearly opaque Gaussians: most pixels saturate after a few entries.
pub(crate) fn saturated_scene() -> OwnedGaussians {
    let mut scene = random_scene_sized(600, 3, 41, -2.0);
    for l in &mut scene.opacity_logits {
        *l += 5.0;
    }
    scene
}

/// Needles (one axis ~30x the others) at random angles: the blend only sees the tiles their
/// 1/255 ellipse reaches (tile_test.wgsl), which drops most of a diagonal needle's bounding
/// box; no pixel may lose a contribution.
#[test]
fn needles_match_reference() {
    let scene = needle_scene();
    for depth in [false, true] {
        let (image, depth_err) = forward_errors(&scene, &camera(90, 70), depth);
        for (what, e) in [("image", image), ("depth", depth_err)] {
            assert!(e.max <= 1e-4, "depth={depth}: {what} error {e:?}");
        }
    }
}

/// Large opaque Gaussians: every pixel stops blending after a few of its tile's hundreds of
/// entries, so the forward's row early-out (all eight pixels stopped) and the backward's walk
/// from the tile's longest consumed prefix (rows and pixels with shorter ones skip entries)
/// both run; partial tiles at the right and bottom edges (90 x 70 is not a multiple of 8).
#[test]
fn saturated_scene_matches_reference() {
    let scene = saturated_scene();
    let cam = camera(90, 70);
    let opts = options(scene.channels, true);
    let reference = reference::forward(&scene.view(), &cam, &opts).unwrap();
    let saturated = reference.alpha.iter().filter(|&&a| a > 0.999).count();
    assert!(
        saturated * 10 >= reference.alpha.len() * 9,
        "only {saturated} of {} pixels saturate: the scene does not test early stops",
        reference.alpha.len()
    );
    let (image, depth_err) = forward_errors(&scene, &cam, true);
    for (what, e) in [("image", image), ("depth", depth_err)] {
        assert!(e.max <= 1e-4, "{what} error {e:?}");
    }
    for path in backward_paths() {
        let (gpu, reference) = gradients(&scene, &cam, true, path);
        let errors = gradient_errors(&gpu, &reference);
        eprintln!("saturated gradients {path:?}: {errors:?}");
        assert!(errors.iter().all(|&e| e < 1e-3), "{path:?}: {errors:?}");
    }
}

// Large frames: an image whose per-pixel buffers or pair lists exceed one storage binding is
// rendered in bands of tile rows (forward.rs); the tests force bands on small images with a
// lower binding limit, and render one real large size.

/// `g` in f64, to compare two f32 results with [`gradient_errors`].
fn widened(g: &GaussianGradients<f32>) -> GaussianGradients<f64> {
    let wide = |v: &[f32]| -> Vec<f64> { v.iter().map(|&x| f64::from(x)).collect() };
    GaussianGradients {
        means: g.means.iter().map(|r| r.map(f64::from)).collect(),
        quats: g.quats.iter().map(|r| r.map(f64::from)).collect(),
        log_scales: g.log_scales.iter().map(|r| r.map(f64::from)).collect(),
        opacity_logits: wide(&g.opacity_logits),
        features: wide(&g.features),
    }
}

/// Renders `scene` whole and in bands under `limit` bytes per binding; asserts the banded
/// images equal the whole ones bit for bit and the gradients agree to f32 summation order
/// (the atomics add in another order); returns the number of bands.
fn banded_matches_whole(scene: &OwnedGaussians, cam: &Camera, depth: bool, limit: u64) -> usize {
    let opts = options(scene.channels, depth);
    let (whole, whole_state) =
        forward_impl(&scene.view(), cam, &opts, ForwardRun::checked(true)).unwrap();
    assert_eq!(whole_state.bands(), 1);
    let (banded, state) = forward_impl(
        &scene.view(),
        cam,
        &opts,
        ForwardRun {
            binding_limit: Some(limit),
            ..ForwardRun::checked(true)
        },
    )
    .unwrap();
    assert!(
        banded == whole,
        "banded images differ from the whole frame's"
    );
    assert_eq!(
        state.pairs, whole_state.pairs,
        "bands hold other tile lists"
    );
    let img = random_image_grads(cam.pixels(), scene.channels, 5);
    let grads = OutputGradients {
        features: &img[0][..],
        alpha: &img[1][..],
        depth: depth.then_some(&img[2][..]),
    };
    for path in backward_paths() {
        let run = |state| {
            backward_impl(state, &grads, path.accumulation, true, path.subgroups, true).unwrap()
        };
        let errors = gradient_errors(&run(&state), &widened(&run(&whole_state)));
        assert!(errors.iter().all(|&e| e < 1e-5), "{path:?}: {errors:?}");
    }
    state.bands()
}

/// 16 rows of 100 pixels of 3 features, alpha and depth fit in the limit, 24 do not: 83 rows
/// (not a multiple of the tile) become six bands, Gaussians straddling their edges.
#[test]
fn image_bands_render_exactly_like_one_frame() {
    let scene = random_scene_sized(400, 3, 31, -3.5);
    let limit = 100 * 5 * 4 * 16 + 100;
    let bands = banded_matches_whole(&scene, &camera(100, 83), true, limit);
    assert_eq!(bands, 6);
}

/// The whole 64 x 64 image (one feature, no depth: two values per pixel) fits in the limit,
/// but its tile-Gaussian pairs do not: the band is halved until each half's pairs fit.
#[test]
fn bands_whose_pairs_overflow_are_halved() {
    let scene = random_scene_sized(700, 1, 7, -1.5);
    let cam = camera(64, 64);
    let limit = 64 * 64 * 2 * 4;
    let (_, state) = super::forward(&scene.view(), &cam, &options(1, false)).unwrap();
    assert!(
        u64::from(state.pairs) * 4 > 2 * limit,
        "{} pairs: too few to need halving twice",
        state.pairs
    );
    let bands = banded_matches_whole(&scene, &cam, false, limit);
    assert!(bands >= 3, "{bands} bands");
}

/// A 3840 x 2160 frame with 3 features and depth (166 MB of images, more than the 128 MiB one
/// storage binding holds on lavapipe and many GPUs) renders on both executors and matches
/// the f64 reference, images and gradients. Few, mostly small Gaussians keep it quick; a
/// few large ones cross the bands' edges.
#[test]
fn large_frame_renders_on_both_executors() {
    let cam = camera(3840, 2160);
    let mut scene = random_scene_sized(150, 3, 17, -6.0);
    for (i, y) in [0.0f32, 0.76, 0.79].iter().enumerate() {
        let features = [0.3, 0.6, 0.9];
        scene.push(
            [0.1 * i as f32, *y, 0.0],
            [1.0, 0.2, 0.0, 0.1],
            [-2.5; 3],
            1.0,
            &features,
        );
    }
    let opts = options(3, true);
    let ctx = GpuContext::global().unwrap();
    let reference = reference::forward(&scene.view(), &cam, &opts).unwrap();
    let (gpu, gpu_state) = super::forward(&scene.view(), &cam, &opts).unwrap();
    let image_bytes = cam.pixels() as u64 * 5 * 4;
    if image_bytes > ctx.info.max_storage_binding_bytes {
        assert!(gpu_state.bands() >= 2, "{} band(s)", gpu_state.bands());
    }
    let (cpu, cpu_state) = super::cpu::forward(&scene.view(), &cam, &opts).unwrap();
    // A handful of pixels sit on the 1/255 alpha cut-off, where f32 and f64 decide apart
    // (as in forward_matches_reference); in depth such a flip weighs z / 255.
    for (name, out) in [("wgpu", &gpu), ("cpu", &cpu)] {
        let image = ImageError::of(&out.features, &reference.features)
            .worst(ImageError::of(&out.alpha, &reference.alpha));
        assert!(image.within_flips(), "{name} image: {image:?}");
        let depth = ImageError::of(
            out.depth.as_ref().unwrap(),
            reference.depth.as_ref().unwrap(),
        );
        assert!(
            depth.over <= 2e-4 && depth.max <= 6.0 / 255.0,
            "{name} depth: {depth:?}"
        );
    }
    let covered = reference.alpha.iter().filter(|&&a| a > 0.01).count();
    assert!(covered > 10_000, "only {covered} pixels covered");

    let img = random_image_grads(cam.pixels(), 3, 11);
    let grads = OutputGradients {
        features: &img[0][..],
        alpha: &img[1][..],
        depth: Some(&img[2][..]),
    };
    let wide: Vec<Vec<f64>> = img
        .iter()
        .map(|v| v.iter().map(|&x| f64::from(x)).collect())
        .collect();
    let wide_grads = OutputGradients {
        features: &wide[0][..],
        alpha: &wide[1][..],
        depth: Some(&wide[2][..]),
    };
    let expected = reference::backward(&scene.view(), &cam, &opts, &wide_grads).unwrap();
    let gpu_grads = super::backward(&gpu_state, &grads, Accumulation::Auto, true, 0).unwrap();
    let cpu_grads = super::cpu::backward(&cpu_state, &grads, true, 0).unwrap();
    for (name, g) in [("wgpu", &gpu_grads), ("cpu", &cpu_grads)] {
        let errors = gradient_errors(g, &expected);
        assert!(errors.iter().all(|&e| e < 1e-3), "{name}: {errors:?}");
    }
}

/// The counting blend renders exactly what the normal one does, and its counters relate to
/// the CPU executor's as designed: `row_evaluations` applies the CPU executor's rule (its
/// binning's row marks, evaluated while the row still blends) to the wgpu walk, and the
/// blending decisions are the contract's, so it and `contributions` equal the CPU executor's
/// `evaluations` and `contributions` up to entries the two executors' tile tests list
/// differently (a widened span barely reaching a tile) and f32 rounding. The wgpu blend decides
/// per quad of four pixels, so the evaluations it makes are at most the row rule's without
/// subgroups, and with subgroups (where a quad one row needs is evaluated by every row of the
/// tile) at least as many as without.
#[test]
fn blend_counters_match_the_cpu_executor() {
    for (width, height, scene) in [
        (100, 75, random_scene(3_000, 3, 41)),
        (128, 96, random_scene_sized(20_000, 3, 43, -5.5)),
    ] {
        let cam = camera(width, height);
        let opts = options(3, true);
        let (_, cpu_state) = super::cpu::forward(&scene.view(), &cam, &opts).unwrap();
        let cpu = cpu_state.stats;
        let mut quad_evaluations = Vec::new();
        for subgroups in subgroup_choices() {
            let view = scene.view();
            let (plain, _) =
                forward_impl(&view, &cam, &opts, ForwardRun::checked(subgroups)).unwrap();
            let (counted, state) = forward_impl(
                &view,
                &cam,
                &opts,
                ForwardRun {
                    counting: true,
                    ..ForwardRun::checked(subgroups)
                },
            )
            .unwrap();
            assert_eq!(
                plain, counted,
                "subgroups {subgroups}: counting changed the images"
            );
            let gpu = state.counts.unwrap();
            eprintln!("{width}x{height} subgroups {subgroups}: wgpu {gpu:?}, cpu {cpu:?}");
            let near = |a: u64, b: u64| a.abs_diff(b) as f64 <= 1e-3 * b as f64;
            assert!(cpu.contributions > 1_000, "{cpu:?}");
            assert!(
                near(gpu.row_evaluations, cpu.evaluations),
                "{gpu:?} {cpu:?}"
            );
            assert!(
                near(gpu.contributions, cpu.contributions),
                "{gpu:?} {cpu:?}"
            );
            assert!(gpu.contributions <= gpu.quad_evaluations, "{gpu:?}");
            if !subgroups {
                assert!(gpu.quad_evaluations <= gpu.row_evaluations, "{gpu:?}");
            }
            quad_evaluations.push(gpu.quad_evaluations);
        }
        assert!(
            quad_evaluations.windows(2).all(|w| w[0] <= w[1]),
            "{quad_evaluations:?}"
        );
    }
}
