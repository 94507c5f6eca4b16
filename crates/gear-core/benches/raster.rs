//! Rasterizer wall time: forward (render + image readback) and backward (gradients + readback)
//! of the wgpu kernels and of the native CPU executor, on random scenes like `python -m gear bench raster` (a unit ball of Gaussians covering its
//! silhouette a few times, depth on), medians of `GEAR_BENCH_REPEATS` (default 7) runs after
//! a warm-up that compiles the pipelines and fills the buffer pool.
//!
//! Also reports the mean process CPU time per call (all threads, from /proc/self/stat on
//! Linux): on a machine shared with other jobs wall time swings with their load, CPU time
//! much less.
//!
//! `cargo bench -p gear-core --bench raster [-- N@SIZE ...]`, e.g. `-- 20000@128`;
//! `GEAR_BENCH_EXEC=cpu` (or `wgpu`) times one executor only.

use std::time::Instant;

use gear_core::splat::{
    backward, cpu, forward, Accumulation, Camera, OutputGradients, OwnedGaussians, RenderOptions,
};

const CHANNELS: usize = 3;
const DEFAULT_CASES: [(usize, u32); 3] = [(20_000, 128), (100_000, 256), (8_000, 64)];

/// Standard normal sample (Box-Muller).
fn normal(rng: &mut fastrand::Rng) -> f32 {
    let u = rng.f32().max(1e-7);
    let v = rng.f32();
    (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
}

/// `n` Gaussians filling a unit ball, sized so `n` disks cover its silhouette ~4 times.
fn ball(n: usize, seed: u64) -> OwnedGaussians {
    let mut rng = fastrand::Rng::with_seed(seed);
    let radius = (2.0 / (n as f32).sqrt()).ln();
    let mut s = OwnedGaussians::new(CHANNELS);
    for _ in 0..n {
        let d = [normal(&mut rng), normal(&mut rng), normal(&mut rng)];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
        let r = rng.f32().cbrt() / len;
        s.means.push([d[0] * r, d[1] * r, d[2] * r]);
        s.quats.push([0.0; 4].map(|_| normal(&mut rng)));
        s.log_scales
            .push([0.0; 3].map(|_| radius + 0.3 * normal(&mut rng)));
        s.opacity_logits.push(normal(&mut rng));
        s.features.extend((0..CHANNELS).map(|_| rng.f32()));
    }
    s
}

/// A square camera 3.5 units from the ball's centre, slightly above it, looking at it.
fn camera(size: u32) -> Camera {
    let eye = glam::Vec3::new(0.0, -0.5, -3.5);
    let forward = (-eye).normalize();
    let right = glam::Vec3::Y.cross(forward).normalize();
    let down = forward.cross(right);
    let t = [-right.dot(eye), -down.dot(eye), -forward.dot(eye)];
    let rows = [right, down, forward];
    let mut world_to_cam = [[0.0, 0.0, 0.0, 1.0]; 4];
    for (row, (axis, tr)) in world_to_cam.iter_mut().zip(rows.iter().zip(t)) {
        *row = [axis.x, axis.y, axis.z, tr];
    }
    let focal = 0.5 * size as f32 / (0.5f32 * 0.75).tan();
    Camera {
        world_to_cam,
        fx: focal,
        fy: focal,
        cx: 0.5 * size as f32,
        cy: 0.5 * size as f32,
        width: size,
        height: size,
    }
}

/// User + system CPU time of this process in milliseconds, if the platform reports it.
fn cpu_ms() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let mut fields = rest.split_whitespace().skip(11);
    let utime: f64 = fields.next()?.parse().ok()?;
    let stime: f64 = fields.next()?.parse().ok()?;
    // Clock ticks are 1/100 s on Linux.
    Some(10.0 * (utime + stime))
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Forward and backward times of one case.
struct Timing {
    /// Median wall milliseconds.
    forward: f64,
    backward: f64,
    /// Mean process CPU milliseconds per call.
    forward_cpu: Option<f64>,
    backward_cpu: Option<f64>,
    pairs: u64,
    /// Gaussian-pixel evaluations per pixel and the fraction blended (CPU executor only).
    evaluations: Option<(f64, f64)>,
}

/// Which executor runs the rasterizer.
#[derive(Debug, Clone, Copy)]
enum Backend {
    Wgpu,
    Cpu,
}

/// Times `repeats` runs (after one warm-up run).
fn time(backend: Backend, n: usize, size: u32, repeats: usize) -> Timing {
    let scene = ball(n, 0);
    let cam = camera(size);
    let options = RenderOptions {
        depth: true,
        background: vec![0.0; CHANNELS],
    };
    let pixels = cam.pixels();
    let grad_features: Vec<f32> = (0..pixels * CHANNELS)
        .map(|i| (i % 7) as f32 * 0.1)
        .collect();
    let grad_alpha = vec![1.0f32; pixels];
    let grad_depth = vec![0.1f32; pixels];
    let grads = OutputGradients {
        features: &grad_features,
        alpha: &grad_alpha,
        depth: Some(&grad_depth),
    };
    let (mut fwd, mut bwd) = (Vec::new(), Vec::new());
    let (mut fwd_cpu, mut bwd_cpu) = (Some(0.0), Some(0.0));
    let mut pairs = 0u64;
    let mut evaluations = None;
    for run in 0..=repeats {
        let cpu0 = cpu_ms();
        let start = Instant::now();
        let (middle, cpu1) = match backend {
            Backend::Wgpu => {
                let (_, state) = forward(&scene.view(), &cam, &options).expect("forward");
                let (middle, cpu1) = (Instant::now(), cpu_ms());
                backward(&state, &grads, Accumulation::Auto, true, 0).expect("backward");
                pairs = state.pairs as u64;
                (middle, cpu1)
            }
            Backend::Cpu => {
                let (_, state) = cpu::forward(&scene.view(), &cam, &options).expect("forward");
                let (middle, cpu1) = (Instant::now(), cpu_ms());
                cpu::backward(&state, &grads, true, 0).expect("backward");
                pairs = state.stats.pairs;
                let s = state.stats;
                evaluations = Some((
                    s.evaluations as f64 / pixels as f64,
                    s.contributions as f64 / s.evaluations.max(1) as f64,
                ));
                (middle, cpu1)
            }
        };
        let end = Instant::now();
        let cpu2 = cpu_ms();
        if run > 0 {
            fwd.push(1e3 * (middle - start).as_secs_f64());
            bwd.push(1e3 * (end - middle).as_secs_f64());
            let spent = |a: Option<f64>, b: Option<f64>| Some(b? - a?);
            fwd_cpu = fwd_cpu.and_then(|t| Some(t + spent(cpu0, cpu1)?));
            bwd_cpu = bwd_cpu.and_then(|t| Some(t + spent(cpu1, cpu2)?));
        }
    }
    Timing {
        forward: median(fwd),
        backward: median(bwd),
        forward_cpu: fwd_cpu.map(|t| t / repeats as f64),
        backward_cpu: bwd_cpu.map(|t| t / repeats as f64),
        pairs,
        evaluations,
    }
}

fn show(ms: Option<f64>) -> String {
    ms.map_or_else(|| "-".into(), |v| format!("{v:.1}"))
}

fn parse_case(arg: &str) -> Option<(usize, u32)> {
    let (n, size) = arg.split_once('@')?;
    Some((n.parse().ok()?, size.parse().ok()?))
}

fn main() {
    let repeats: usize = std::env::var("GEAR_BENCH_REPEATS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(7);
    // cargo passes `--bench`; anything of the form N@SIZE selects cases.
    let mut cases: Vec<(usize, u32)> = std::env::args()
        .skip(1)
        .filter_map(|a| parse_case(&a))
        .collect();
    if cases.is_empty() {
        cases = DEFAULT_CASES.to_vec();
    }
    println!("{repeats} runs, C={CHANNELS}, depth on; wall: median ms, cpu: mean ms per call");
    println!(
        "{:>8} {:>9} {:>5} {:>9} | {:>8} {:>8} | {:>8} {:>8} | {:>7} {:>6}",
        "N",
        "image",
        "exec",
        "pairs",
        "fwd wall",
        "bwd wall",
        "fwd cpu",
        "bwd cpu",
        "eval/px",
        "useful"
    );
    // GEAR_BENCH_EXEC=cpu or wgpu times one executor only (e.g. under a profiler).
    let only = std::env::var("GEAR_BENCH_EXEC").unwrap_or_default();
    let backends: Vec<Backend> = [Backend::Wgpu, Backend::Cpu]
        .into_iter()
        .filter(|b| only.is_empty() || format!("{b:?}").eq_ignore_ascii_case(&only))
        .collect();
    for (n, size) in cases {
        for &backend in &backends {
            let t = time(backend, n, size, repeats);
            let name = format!("{backend:?}").to_lowercase();
            let (per_pixel, useful) = t.evaluations.map_or_else(
                || ("-".into(), "-".into()),
                |(e, u)| (format!("{e:.1}"), format!("{:.0}%", 100.0 * u)),
            );
            println!(
                "{n:>8} {size:>4}x{size:<4} {name:>5} {:>9} | {:>8.1} {:>8.1} | {:>8} {:>8} | {per_pixel:>7} {useful:>6}",
                t.pairs,
                t.forward,
                t.backward,
                show(t.forward_cpu),
                show(t.backward_cpu)
            );
        }
    }
}
