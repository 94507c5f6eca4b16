//! Bindings of the rasterizer (gear_core::splat): the GPU (wgpu) and native CPU executors'
//! forward passes, their shared backward, and the f64 CPU reference pair, with the signatures
//! of the rasterizer contract. Forward returns the images plus an opaque `RasterState` that
//! backward consumes; the GPU state keeps the device buffers backward replays, the CPU state
//! the tile lists and pixel state, the reference state copies of the inputs.

use gear_core::splat::{
    self, cpu, reference, Accumulation, Camera, ForwardState, GaussianGradients, Gaussians,
    OutputGradients, OwnedGaussians, RenderOptions, RenderOutput,
};
use numpy::{Element, PyArray1, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::args::{array, has_dtype, Dim, Dtype};
use crate::errors::guarded;

/// Owned inputs of a reference forward pass, replayed by its backward.
pub(crate) struct ReferenceInputs {
    gaussians: OwnedGaussians,
    camera: Camera,
    options: RenderOptions,
}

pub(crate) enum StateKind {
    Gpu(Box<ForwardState>),
    Cpu(Box<cpu::CpuState>),
    Reference(Box<ReferenceInputs>),
}

/// What `rasterize_backward` / `reference_backward` need from the matching forward call.
#[pyclass(frozen, name = "RasterState", module = "gear._core")]
pub struct RasterState {
    kind: StateKind,
    width: u32,
    height: u32,
    channels: usize,
    depth: bool,
    /// GPU backward accumulates with compare-and-swap even where float32 atomics exist.
    force_cas: bool,
}

#[pymethods]
impl RasterState {
    fn __repr__(&self) -> String {
        let kind = match self.kind {
            StateKind::Gpu(_) => "gpu",
            StateKind::Cpu(_) => "cpu",
            StateKind::Reference(_) => "reference",
        };
        format!(
            "RasterState({kind}, {}x{}, channels={}, depth={})",
            self.width, self.height, self.channels, self.depth
        )
    }

    /// What the forward pass did: `pairs` ((tile, Gaussian) pairs) for the GPU and CPU
    /// executors; for the CPU also `evaluations` and `contributions` (Gaussian-pixel
    /// evaluations of the blend and those blended), `state_bytes` (held by this state) and
    /// `backward_bytes` (allocated by a backward with feature gradients); for the GPU after
    /// `rasterize_forward_counted` also `evaluations` (those its blend made, by quads of four
    /// pixels), `row_evaluations` (the CPU executor's rule applied to the same walk) and
    /// `contributions`. Empty for the reference.
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        match &self.kind {
            StateKind::Gpu(state) => {
                d.set_item("pairs", state.pairs)?;
                if let Some(counts) = state.counts {
                    d.set_item("evaluations", counts.quad_evaluations)?;
                    d.set_item("row_evaluations", counts.row_evaluations)?;
                    d.set_item("contributions", counts.contributions)?;
                }
            }
            StateKind::Cpu(state) => {
                let s = state.stats;
                d.set_item("pairs", s.pairs)?;
                d.set_item("evaluations", s.evaluations)?;
                d.set_item("contributions", s.contributions)?;
                d.set_item("state_bytes", s.state_bytes)?;
                d.set_item("backward_bytes", cpu::backward_bytes(state, true))?;
            }
            StateKind::Reference(_) => {}
        }
        Ok(d)
    }
}

/// The forward arguments, checked and borrowed from numpy.
pub(crate) struct ForwardArgs<'py> {
    arrays: [numpy::PyReadonlyArrayDyn<'py, f32>; 5],
    channels: usize,
    camera: Camera,
    options: RenderOptions,
}

impl ForwardArgs<'_> {
    fn slices(&self) -> PyResult<[&[f32]; 5]> {
        let [a, b, c, d, e] = &self.arrays;
        Ok([
            a.as_slice()?,
            b.as_slice()?,
            c.as_slice()?,
            d.as_slice()?,
            e.as_slice()?,
        ])
    }
}

/// A camera from its world-to-camera matrix (float32 [4, 4]), (fx, fy, cx, cy) and image size.
pub(crate) fn camera(
    world_to_cam: &Bound<'_, PyAny>,
    (fx, fy, cx, cy): (f32, f32, f32, f32),
    width: u32,
    height: u32,
) -> PyResult<Camera> {
    let w2c = array::<f32>(
        world_to_cam,
        "world_to_cam",
        &[Dim::Fixed(4), Dim::Fixed(4)],
    )?;
    let w2c = w2c.as_slice()?;
    Ok(Camera {
        world_to_cam: std::array::from_fn(|r| std::array::from_fn(|c| w2c[4 * r + c])),
        fx,
        fy,
        cx,
        cy,
        width,
        height,
    })
}

/// The five Gaussian arrays of the rasterizer contract, checked, and their channel count.
pub(crate) fn gaussian_arrays<'py>(
    means: &Bound<'py, PyAny>,
    quats: &Bound<'py, PyAny>,
    log_scales: &Bound<'py, PyAny>,
    opacity_logits: &Bound<'py, PyAny>,
    features: &Bound<'py, PyAny>,
) -> PyResult<([numpy::PyReadonlyArrayDyn<'py, f32>; 5], usize)> {
    let n = Dim::Any("N");
    let features = array::<f32>(features, "features", &[n, Dim::Any("C")])?;
    let channels = features.shape()[1];
    let arrays = [
        array::<f32>(means, "means", &[n, Dim::Fixed(3)])?,
        array::<f32>(quats, "quats", &[n, Dim::Fixed(4)])?,
        array::<f32>(log_scales, "log_scales", &[n, Dim::Fixed(3)])?,
        array::<f32>(opacity_logits, "opacity_logits", &[n])?,
        features,
    ];
    Ok((arrays, channels))
}

#[allow(clippy::too_many_arguments)]
pub(crate) fn forward_args<'py>(
    means: &Bound<'py, PyAny>,
    quats: &Bound<'py, PyAny>,
    log_scales: &Bound<'py, PyAny>,
    opacity_logits: &Bound<'py, PyAny>,
    features: &Bound<'py, PyAny>,
    world_to_cam: &Bound<'py, PyAny>,
    intrinsics: (f32, f32, f32, f32),
    width: u32,
    height: u32,
    background: &Bound<'py, PyAny>,
    depth: bool,
) -> PyResult<ForwardArgs<'py>> {
    let (arrays, channels) = gaussian_arrays(means, quats, log_scales, opacity_logits, features)?;
    let camera = camera(world_to_cam, intrinsics, width, height)?;
    let background = array::<f32>(background, "background", &[Dim::Fixed(channels)])?;
    let options = RenderOptions {
        depth,
        background: background.as_slice()?.to_vec(),
    };
    Ok(ForwardArgs {
        arrays,
        channels,
        camera,
        options,
    })
}

type Images<'py> = (
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Option<Bound<'py, PyAny>>,
);

/// Images as numpy arrays: features [H, W, C], alpha [H, W], depth [H, W] or None.
fn images<'py, T: Element>(
    py: Python<'py>,
    out: RenderOutput<T>,
    width: u32,
    height: u32,
    channels: usize,
) -> PyResult<Images<'py>> {
    let (h, w) = (height as usize, width as usize);
    let features = PyArray1::from_vec(py, out.features).reshape([h, w, channels])?;
    let alpha = PyArray1::from_vec(py, out.alpha).reshape([h, w])?;
    let depth = out
        .depth
        .map(|d| PyArray1::from_vec(py, d).reshape([h, w]))
        .transpose()?;
    Ok((
        features.into_any(),
        alpha.into_any(),
        depth.map(Bound::into_any),
    ))
}

type Gradients<'py> = (
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Option<Bound<'py, PyAny>>,
);

/// Gradients as numpy arrays shaped like the inputs; the features' only when
/// `features_grad` (else None: they were not computed).
fn gradients<'py, T: Element + Copy>(
    py: Python<'py>,
    g: GaussianGradients<T>,
    channels: usize,
    features_grad: bool,
) -> PyResult<Gradients<'py>> {
    let n = g.opacity_logits.len();
    let flat = |rows: Vec<T>, width: usize| PyArray1::from_vec(py, rows).reshape([n, width]);
    Ok((
        flat(g.means.into_flattened(), 3)?.into_any(),
        flat(g.quats.into_flattened(), 4)?.into_any(),
        flat(g.log_scales.into_flattened(), 3)?.into_any(),
        PyArray1::from_vec(py, g.opacity_logits).into_any(),
        features_grad
            .then(|| flat(g.features, channels))
            .transpose()?
            .map(Bound::into_any),
    ))
}

pub(crate) type ForwardResult<'py> = (
    Bound<'py, PyAny>,
    Bound<'py, PyAny>,
    Option<Bound<'py, PyAny>>,
    RasterState,
);

/// What every forward binding does around its renderer: borrow the checked arrays as
/// Gaussians, run `render` (GIL released; it returns the images and the state its backward
/// needs), and return its images as numpy arrays with a `RasterState` around the state it made.
pub(crate) fn forward_result<'py, T: Element + Send>(
    py: Python<'py>,
    args: &ForwardArgs<'py>,
    force_cas: bool,
    render: impl FnOnce(
            Gaussians<'_>,
            &Camera,
            &RenderOptions,
        ) -> gear_core::Result<(RenderOutput<T>, StateKind)>
        + Send,
) -> PyResult<ForwardResult<'py>> {
    let [means, quats, log_scales, opacity_logits, features] = args.slices()?;
    let (camera, options, channels) = (&args.camera, &args.options, args.channels);
    let (out, kind) = guarded(py, || {
        let gaussians =
            Gaussians::from_flat(means, quats, log_scales, opacity_logits, features, channels)?;
        render(gaussians, camera, options)
    })?;
    let (width, height) = (args.camera.width, args.camera.height);
    let (f, a, d) = images(py, out, width, height, channels)?;
    let state = RasterState {
        kind,
        width,
        height,
        channels,
        depth: args.options.depth,
        force_cas,
    };
    Ok((f, a, d, state))
}

/// Declares a forward binding with the rasterizer contract's signature, after the leading
/// parameters given in parentheses (none but for the render over a static layer): it checks
/// the arguments and hands them to `forward_result` with `$render` (a renderer of the
/// Gaussians, camera and options, which may use the leading parameters). One declaration
/// serves every forward binding, so their signatures cannot drift apart.
macro_rules! forward_binding {
    ($(#[$doc:meta])* $name:ident($($lead:ident: $lead_ty:ty),*) => $render:expr) => {
        $(#[$doc])*
        #[pyfunction]
        #[pyo3(signature = ($($lead,)* means, quats, log_scales, opacity_logits, features, world_to_cam, intrinsics, width, height, background, depth, force_cas=false))]
        #[allow(clippy::too_many_arguments)]
        fn $name<'py>(
            py: Python<'py>,
            $($lead: $lead_ty,)*
            means: &Bound<'py, PyAny>,
            quats: &Bound<'py, PyAny>,
            log_scales: &Bound<'py, PyAny>,
            opacity_logits: &Bound<'py, PyAny>,
            features: &Bound<'py, PyAny>,
            world_to_cam: &Bound<'py, PyAny>,
            intrinsics: (f32, f32, f32, f32),
            width: u32,
            height: u32,
            background: &Bound<'py, PyAny>,
            depth: bool,
            force_cas: bool,
        ) -> PyResult<ForwardResult<'py>> {
            let args = forward_args(
                means,
                quats,
                log_scales,
                opacity_logits,
                features,
                world_to_cam,
                intrinsics,
                width,
                height,
                background,
                depth,
            )?;
            forward_result(py, &args, force_cas, $render)
        }
    };
}
pub(crate) use forward_binding;

fn render_gpu(
    gaussians: Gaussians<'_>,
    camera: &Camera,
    options: &RenderOptions,
) -> gear_core::Result<(RenderOutput<f32>, StateKind)> {
    let (out, state) = splat::forward(&gaussians, camera, options)?;
    Ok((out, StateKind::Gpu(Box::new(state))))
}

/// As [`render_gpu`] with the counting variant of the blend (its counters in the state).
fn render_gpu_counted(
    gaussians: Gaussians<'_>,
    camera: &Camera,
    options: &RenderOptions,
) -> gear_core::Result<(RenderOutput<f32>, StateKind)> {
    let (out, state) = splat::forward_counted(&gaussians, camera, options)?;
    Ok((out, StateKind::Gpu(Box::new(state))))
}

fn render_cpu(
    gaussians: Gaussians<'_>,
    camera: &Camera,
    options: &RenderOptions,
) -> gear_core::Result<(RenderOutput<f32>, StateKind)> {
    let (out, state) = cpu::forward(&gaussians, camera, options)?;
    Ok((out, StateKind::Cpu(Box::new(state))))
}

/// The reference render, keeping copies of the inputs for its backward.
fn render_reference(
    gaussians: Gaussians<'_>,
    camera: &Camera,
    options: &RenderOptions,
) -> gear_core::Result<(RenderOutput<f64>, StateKind)> {
    let out = reference::forward(&gaussians, camera, options)?;
    let inputs = ReferenceInputs {
        gaussians: gaussians.into(),
        camera: *camera,
        options: options.clone(),
    };
    Ok((out, StateKind::Reference(Box::new(inputs))))
}

forward_binding!(
    /// Renders on the GPU. `force_cas` makes the later backward accumulate with the
    /// compare-and-swap loop even where float32 atomics exist (to test that path).
    rasterize_forward() => render_gpu
);

forward_binding!(
    /// `rasterize_forward` with the blend's work counters (a slower variant, for benchmarks):
    /// its state's `stats()` has them too.
    rasterize_forward_counted() => render_gpu_counted
);

forward_binding!(
    /// Renders with the native CPU executor (threads: `GEAR_THREADS`, default every core);
    /// same arguments as `rasterize_forward` (`force_cas` is accepted and ignored). Its
    /// backward is `rasterize_backward` too.
    rasterize_forward_cpu() => render_cpu
);

forward_binding!(
    /// Renders with the f64 CPU reference (outputs float64); same arguments as
    /// `rasterize_forward` (`force_cas` is accepted and ignored).
    reference_forward() => render_reference
);

/// Image gradients as checked numpy views of element type `T`.
struct ImageGrads<'py, T: Element> {
    features: numpy::PyReadonlyArrayDyn<'py, T>,
    alpha: numpy::PyReadonlyArrayDyn<'py, T>,
    depth: Option<numpy::PyReadonlyArrayDyn<'py, T>>,
}

impl<T: Element> ImageGrads<'_, T> {
    fn view(&self) -> PyResult<OutputGradients<'_, T>> {
        Ok(OutputGradients {
            features: self.features.as_slice()?,
            alpha: self.alpha.as_slice()?,
            depth: self.depth.as_ref().map(|d| d.as_slice()).transpose()?,
        })
    }
}

fn image_grads<'py, T: Dtype>(
    state: &RasterState,
    grad_features: &Bound<'py, PyAny>,
    grad_alpha: &Bound<'py, PyAny>,
    grad_depth: Option<&Bound<'py, PyAny>>,
) -> PyResult<ImageGrads<'py, T>> {
    let (h, w) = (
        Dim::Fixed(state.height as usize),
        Dim::Fixed(state.width as usize),
    );
    Ok(ImageGrads {
        features: array::<T>(
            grad_features,
            "grad_features",
            &[h, w, Dim::Fixed(state.channels)],
        )?,
        alpha: array::<T>(grad_alpha, "grad_alpha", &[h, w])?,
        depth: grad_depth
            .filter(|d| !d.is_none())
            .map(|d| array::<T>(d, "grad_depth", &[h, w]))
            .transpose()?,
    })
}

fn wrong_state(expected: &str) -> PyErr {
    PyTypeError::new_err(format!(
        "argument 'state': expected the state returned by {expected}"
    ))
}

/// Gradients of the GPU or CPU render that produced `state` (float32 arrays shaped like the
/// inputs). With `features_grad=False` the feature gradients are skipped (returned as None),
/// which is cheaper and leaves the other gradients unchanged. The first `held` Gaussians are
/// constants of the caller: their gradients come back as zeros (the CPU executor skips their
/// work; the others are unchanged).
#[pyfunction]
#[pyo3(signature = (state, grad_features, grad_alpha, grad_depth=None, features_grad=true, held=0))]
fn rasterize_backward<'py>(
    py: Python<'py>,
    state: &Bound<'py, RasterState>,
    grad_features: &Bound<'py, PyAny>,
    grad_alpha: &Bound<'py, PyAny>,
    grad_depth: Option<&Bound<'py, PyAny>>,
    features_grad: bool,
    held: usize,
) -> PyResult<Gradients<'py>> {
    let state = state.get();
    let grads = image_grads::<f32>(state, grad_features, grad_alpha, grad_depth)?;
    let view = grads.view()?;
    let accumulation = if state.force_cas {
        Accumulation::CompareAndSwap
    } else {
        Accumulation::Auto
    };
    let g = match &state.kind {
        StateKind::Gpu(forward) => guarded(py, || {
            splat::backward(forward, &view, accumulation, features_grad, held)
        })?,
        StateKind::Cpu(forward) => {
            guarded(py, || cpu::backward(forward, &view, features_grad, held))?
        }
        StateKind::Reference(_) => {
            return Err(wrong_state("rasterize_forward or rasterize_forward_cpu"))
        }
    };
    gradients(py, g, state.channels, features_grad)
}

/// Gradients of the reference render that produced `state` (float64; image gradients may be
/// float64 or float32).
#[pyfunction]
#[pyo3(signature = (state, grad_features, grad_alpha, grad_depth=None))]
fn reference_backward<'py>(
    py: Python<'py>,
    state: &Bound<'py, RasterState>,
    grad_features: &Bound<'py, PyAny>,
    grad_alpha: &Bound<'py, PyAny>,
    grad_depth: Option<&Bound<'py, PyAny>>,
) -> PyResult<Gradients<'py>> {
    let state = state.get();
    let StateKind::Reference(inputs) = &state.kind else {
        return Err(wrong_state("reference_forward"));
    };
    let is_f32 = has_dtype::<f32>(grad_features);
    // Keeps whichever form the gradients arrived in alive while `view` borrows it.
    let widened: [Vec<f64>; 3];
    let as_f64;
    let view = if is_f32 {
        let narrow = image_grads::<f32>(state, grad_features, grad_alpha, grad_depth)?;
        let v = narrow.view()?;
        let widen = |s: &[f32]| s.iter().map(|&x| f64::from(x)).collect::<Vec<f64>>();
        widened = [
            widen(v.features),
            widen(v.alpha),
            widen(v.depth.unwrap_or_default()),
        ];
        OutputGradients {
            features: &widened[0][..],
            alpha: &widened[1][..],
            depth: v.depth.map(|_| &widened[2][..]),
        }
    } else {
        as_f64 = image_grads::<f64>(state, grad_features, grad_alpha, grad_depth)?;
        as_f64.view()?
    };
    let g = guarded(py, || {
        reference::backward(
            &inputs.gaussians.view(),
            &inputs.camera,
            &inputs.options,
            &view,
        )
    })?;
    gradients(py, g, state.channels, true)
}

/// Threads of the CPU executor's pool: `GEAR_THREADS`, default every core (a bad value is an
/// error naming it).
#[pyfunction]
fn cpu_threads(py: Python<'_>) -> PyResult<usize> {
    guarded(py, cpu::thread_count)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RasterState>()?;
    m.add_function(wrap_pyfunction!(rasterize_forward, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_forward_counted, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_forward_cpu, m)?)?;
    m.add_function(wrap_pyfunction!(cpu_threads, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_backward, m)?)?;
    m.add_function(wrap_pyfunction!(reference_forward, m)?)?;
    m.add_function(wrap_pyfunction!(reference_backward, m)?)?;
    Ok(())
}
