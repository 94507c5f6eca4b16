//! The op's tests: the f64 reference against independent facts (orthonormality of the basis on
//! the sphere, finite differences of its gradients), then the CPU and GPU executors against
//! the reference at every degree, with the hard cases (zero and tiny directions, huge
//! directions and coefficients, N = 0), and the kernels' declarations against their WGSL.

use super::basis::{basis, unit, C0, MAX_COEFFS};
use super::*;
use crate::splat::kernel_dispatch::KernelParams;

/// Random inputs: `n` Gaussians at `degree`, directions of mixed lengths with every hard
/// case among them, coefficients in [-scale, scale].
fn scene(n: usize, degree: u32, scale: f32, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = fastrand::Rng::with_seed(seed);
    let mut u = |lo: f32, hi: f32| lo + (hi - lo) * rng.f32();
    let k = coefficient_count(degree);
    let mut dirs = Vec::with_capacity(3 * n);
    for i in 0..n {
        let d = [u(-1.0, 1.0), u(-1.0, 1.0), u(-1.0, 1.0)];
        let length = match i % 8 {
            0 => 0.0,   // the camera at the Gaussian's centre
            1 => 1e-14, // below MIN_DIR_NORM
            2 => 1e-9,  // just above it
            3 => 1e30,  // squared components would overflow f32
            _ => u(0.1, 10.0),
        };
        dirs.extend(d.iter().map(|c| c * length));
    }
    let coeffs = (0..n * k * 3).map(|_| u(-scale, scale)).collect();
    let grad_rgb = (0..3 * n).map(|_| u(-1.0, 1.0)).collect();
    (dirs, coeffs, grad_rgb)
}

fn widen(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

/// Each Gaussian's unclamped colour in f64, for the tests' tolerances.
fn unclamped(dirs: &[f64], coeffs: &[f64], degree: u32, i: usize) -> [f64; 3] {
    let k = coefficient_count(degree);
    let d = [dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]];
    let y = basis(unit(d).map_or([0.0; 3], |(u, _)| u), k);
    std::array::from_fn(|ch| {
        0.5 + (0..k)
            .map(|j| y[j] * coeffs[3 * (i * k + j) + ch])
            .sum::<f64>()
    })
}

/// Compares an executor's forward and backward with the reference's on the same inputs.
/// Tolerances are relative to each Gaussian's magnitude (1 + sum |coeffs|), and the gradients
/// of a Gaussian whose unclamped colour is within rounding of the clamp are not compared (f32
/// and f64 may fall on either side of it).
fn check_executor(
    name: &str,
    forward: fn(&ShInput<'_, f32>) -> crate::Result<Vec<f32>>,
    backward: fn(&ShInput<'_, f32>, &[f32]) -> crate::Result<ShGradients<f32>>,
) {
    for degree in 0..=MAX_DEGREE {
        // 20,000 Gaussians span several of the CPU executor's parallel chunks.
        for (n, scale) in [
            (0usize, 1.0f32),
            (1, 1.0),
            (1000, 1.0),
            (333, 1e6),
            (20_000, 1.0),
        ] {
            let (dirs, coeffs, grad_rgb) = scene(n, degree, scale, 17 + u64::from(degree));
            let input = ShInput {
                dirs: &dirs,
                coeffs: &coeffs,
                degree,
            };
            let (dirs64, coeffs64, grad64) = (widen(&dirs), widen(&coeffs), widen(&grad_rgb));
            let wide = ShInput {
                dirs: &dirs64,
                coeffs: &coeffs64,
                degree,
            };
            let rgb = forward(&input).unwrap();
            let want = reference::forward(&wide).unwrap();
            let grads = backward(&input, &grad_rgb).unwrap();
            let want_grads = reference::backward(&wide, &grad64).unwrap();
            assert_eq!(rgb.len(), 3 * n, "{name}");
            assert_eq!(grads.coeffs.len(), coeffs.len(), "{name}");
            assert_eq!(grads.dirs.len(), dirs.len(), "{name}");
            let k = coefficient_count(degree);
            for i in 0..n {
                let label = format!("{name} degree {degree} n {n} scale {scale} Gaussian {i}");
                let row = &coeffs64[i * k * 3..(i + 1) * k * 3];
                let magnitude = 1.0 + row.iter().map(|c| c.abs()).sum::<f64>();
                for ch in 0..3 {
                    let (got, exp) = (f64::from(rgb[3 * i + ch]), want[3 * i + ch]);
                    assert!(got.is_finite(), "{label}: rgb {got}");
                    assert!(
                        (got - exp).abs() <= 2e-6 * magnitude,
                        "{label}: rgb {got} vs {exp}"
                    );
                }
                for g in &grads.coeffs[i * k * 3..(i + 1) * k * 3] {
                    assert!(g.is_finite(), "{label}: coefficient gradient {g}");
                }
                for g in &grads.dirs[3 * i..3 * i + 3] {
                    assert!(g.is_finite(), "{label}: direction gradient {g}");
                }
                let pre = unclamped(&dirs64, &coeffs64, degree, i);
                if pre.iter().any(|p| p.abs() < 1e-4 * magnitude) {
                    continue;
                }
                for j in 0..k * 3 {
                    let (got, exp) = (
                        f64::from(grads.coeffs[i * k * 3 + j]),
                        want_grads.coeffs[i * k * 3 + j],
                    );
                    assert!(
                        (got - exp).abs() <= 2e-6,
                        "{label}: coefficient gradient {j}: {got} vs {exp}"
                    );
                }
                let norm = dirs64[3 * i..3 * i + 3]
                    .iter()
                    .map(|c| c * c)
                    .sum::<f64>()
                    .sqrt();
                let bound = if norm > 0.0 { magnitude / norm } else { 0.0 };
                for a in 0..3 {
                    let (got, exp) = (f64::from(grads.dirs[3 * i + a]), want_grads.dirs[3 * i + a]);
                    assert!(
                        (got - exp).abs() <= 2e-5 * bound.max(f64::MIN_POSITIVE),
                        "{label}: direction gradient {a}: {got} vs {exp}"
                    );
                }
            }
        }
    }
}

#[test]
fn cpu_matches_reference() {
    check_executor("cpu", cpu::forward, cpu::backward);
}

#[test]
fn gpu_matches_reference() {
    check_executor("gpu", gpu::forward, gpu::backward);
}

#[test]
fn basis_is_orthonormal_on_the_sphere() {
    // Midpoint rule in (theta, phi): integral of Y_i Y_j over the sphere is delta_ij.
    let (rows, cols) = (400, 800);
    let mut gram = [[0.0f64; MAX_COEFFS]; MAX_COEFFS];
    let (dt, dp) = (
        std::f64::consts::PI / rows as f64,
        std::f64::consts::TAU / cols as f64,
    );
    for r in 0..rows {
        let theta = (r as f64 + 0.5) * dt;
        let weight = theta.sin() * dt * dp;
        for c in 0..cols {
            let phi = (c as f64 + 0.5) * dp;
            let u = [
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            ];
            let y = basis(u, MAX_COEFFS);
            for i in 0..MAX_COEFFS {
                for j in 0..MAX_COEFFS {
                    gram[i][j] += weight * y[i] * y[j];
                }
            }
        }
    }
    for (i, row) in gram.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            let expected = if i == j { 1.0 } else { 0.0 };
            assert!((v - expected).abs() < 1e-4, "<Y{i}, Y{j}> = {v}");
        }
    }
}

#[test]
fn reference_gradients_match_finite_differences() {
    let h = 1e-6;
    for degree in 0..=MAX_DEGREE {
        let (dirs, coeffs, grad_rgb) = scene(64, degree, 1.0, 5);
        let (mut dirs, mut coeffs, upstream) = (widen(&dirs), widen(&coeffs), widen(&grad_rgb));
        let loss = |dirs: &[f64], coeffs: &[f64]| -> f64 {
            let rgb = reference::forward(&ShInput {
                dirs,
                coeffs,
                degree,
            })
            .unwrap();
            rgb.iter().zip(&upstream).map(|(a, b)| a * b).sum()
        };
        let input = ShInput {
            dirs: &dirs,
            coeffs: &coeffs,
            degree,
        };
        let grads = reference::backward(&input, &upstream).unwrap();
        let k = coefficient_count(degree);
        let near_clamp = |dirs: &[f64], coeffs: &[f64], i: usize| {
            unclamped(dirs, coeffs, degree, i)
                .iter()
                .any(|p| p.abs() < 1e-3)
        };
        for i in 0..64 {
            // Lengths at or near MIN_DIR_NORM (cases 0..2) have no usable difference quotient,
            // and 1e30 needs a step of its own size: the smooth cases are checked.
            if i % 8 < 4 || near_clamp(&dirs, &coeffs, i) {
                continue;
            }
            for j in 0..k * 3 {
                let idx = i * k * 3 + j;
                let old = coeffs[idx];
                coeffs[idx] = old + h;
                let plus = loss(&dirs, &coeffs);
                coeffs[idx] = old - h;
                let minus = loss(&dirs, &coeffs);
                coeffs[idx] = old;
                let fd = (plus - minus) / (2.0 * h);
                assert!(
                    (fd - grads.coeffs[idx]).abs() < 1e-6,
                    "degree {degree} Gaussian {i} coefficient {j}: fd {fd} vs {}",
                    grads.coeffs[idx]
                );
            }
            for a in 0..3 {
                let idx = 3 * i + a;
                let old = dirs[idx];
                dirs[idx] = old + h;
                let plus = loss(&dirs, &coeffs);
                dirs[idx] = old - h;
                let minus = loss(&dirs, &coeffs);
                dirs[idx] = old;
                let fd = (plus - minus) / (2.0 * h);
                assert!(
                    (fd - grads.dirs[idx]).abs() < 1e-5,
                    "degree {degree} Gaussian {i} direction {a}: fd {fd} vs {}",
                    grads.dirs[idx]
                );
            }
        }
    }
}

#[test]
fn short_directions_keep_only_the_constant_term() {
    for executor in [cpu::forward, gpu::forward] {
        let dirs = [0.0f32, 0.0, 0.0, 1e-14, -1e-14, 0.0];
        let coeffs: Vec<f32> = (0..2 * 16 * 3).map(|i| (i % 7) as f32 - 3.0).collect();
        let rgb = executor(&ShInput {
            dirs: &dirs,
            coeffs: &coeffs,
            degree: 3,
        })
        .unwrap();
        for i in 0..2 {
            for ch in 0..3 {
                let expected = (0.5 + C0 * f64::from(coeffs[i * 48 + ch])).max(0.0);
                assert!((f64::from(rgb[3 * i + ch]) - expected).abs() < 1e-6);
            }
        }
    }
}

#[test]
fn bad_inputs_are_clear_errors() {
    let dirs = [1.0f32, 0.0, 0.0];
    let coeffs = [0.0f32; 12];
    let check = |input: ShInput<'_, f32>, needle: &str| {
        for result in [
            cpu::forward(&input).map(|_| ()),
            gpu::forward(&input).map(|_| ()),
        ] {
            let message = result.unwrap_err().to_string();
            assert!(message.contains(needle), "{message}");
        }
    };
    let with = |dirs, coeffs, degree| ShInput {
        dirs,
        coeffs,
        degree,
    };
    check(with(&dirs, &coeffs, 4), "degree must be 0..=3");
    check(with(&dirs, &coeffs, 2), "N x 9 x 3");
    check(with(&dirs[..2], &coeffs[..0], 0), "N x 3");
    check(
        with(&[f32::NAN, 0.0, 0.0], &coeffs, 1),
        "dirs has a non-finite",
    );
    check(
        with(&dirs, &[f32::INFINITY; 12], 1),
        "coeffs has a non-finite",
    );
    let input = with(&dirs, &coeffs, 1);
    let message = cpu::backward(&input, &[0.0; 2]).unwrap_err().to_string();
    assert!(message.contains("grad_rgb"), "{message}");
}

#[test]
fn params_and_workgroup_sizes_match_the_shaders() {
    for degree in 0..=MAX_DEGREE {
        for spec in [gpu::forward_kernel(degree), gpu::backward_kernel(degree)] {
            let label = format!("{} degree {degree}", spec.name);
            let module = naga::front::wgsl::parse_str(&spec.specialised_source())
                .unwrap_or_else(|e| panic!("{label}: {e}"));
            let mut layouter = naga::proc::Layouter::default();
            layouter.update(module.to_ctx()).unwrap();
            let mut uniforms = 0;
            for (_, global) in module.global_variables.iter() {
                let Some(binding) = &global.binding else {
                    continue;
                };
                assert_eq!(binding.group, 0, "{label}");
                if global.space != naga::AddressSpace::Uniform {
                    continue;
                }
                uniforms += 1;
                let name = module.types[global.ty].name.clone().unwrap_or_default();
                assert_eq!(name, gpu::ShParams::WGSL_NAME, "{label}");
                assert_eq!(binding.binding, gpu::ShParams::BINDING, "{label}");
                assert_eq!(
                    layouter[global.ty].size as usize,
                    std::mem::size_of::<gpu::ShParams>(),
                    "{label}"
                );
            }
            assert_eq!(uniforms, 1, "{label}");
            let entry = &module.entry_points[0];
            assert_eq!(entry.workgroup_size, [gpu::WG, 1, 1], "{label}");
        }
    }
}
