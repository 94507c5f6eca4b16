//! Adapter choice and the process-wide [`GpuContext`].

use std::sync::OnceLock;

use crate::error::{GearError, Result};

use super::buffers::BufferPool;
use super::pipelines::PipelineCache;

/// Optional device features that kernels can exploit when present.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OptionalFeatures {
    /// `atomic<f32>` with `atomicAdd` in storage buffers (gradient accumulation without CAS).
    pub float32_atomics: bool,
    /// Subgroup operations (the blend kernels share each Gaussian's loads, and blend-backward
    /// its atomics, between the rows of a tile with them).
    pub subgroups: bool,
    /// GPU timestamps (reported; benchmarks time on the host).
    pub timestamps: bool,
}

/// What `gear info` shows about the adapter in use.
#[derive(Debug, Clone)]
pub struct AdapterInfo {
    pub name: String,
    pub backend: String,
    pub device_type: String,
    pub driver: String,
    pub features: OptionalFeatures,
    pub max_storage_binding_bytes: u64,
    pub max_workgroups_per_dim: u32,
    pub max_storage_buffers_per_stage: u32,
}

/// One wgpu device for the whole process, with its caches.
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: AdapterInfo,
    pub pipelines: PipelineCache,
    pub buffers: BufferPool,
}

const INSTALL_HINT: &str = "no GPU adapter found: gear needs a Vulkan (or Metal/DX12) driver. \
On Debian/Ubuntu install Mesa's software Vulkan driver with \
`apt-get install mesa-vulkan-drivers` (or your GPU vendor's driver), then retry.";

static CONTEXT: OnceLock<std::result::Result<GpuContext, String>> = OnceLock::new();

impl GpuContext {
    /// The process-wide context, created on first use. `GEAR_ADAPTER` (`cpu`, `gpu`, or a
    /// substring of the adapter name) forces a choice; `GEAR_DISABLE_FEATURES` (a comma list of
    /// `float32_atomics`, `subgroups`, `timestamps`) leaves optional features off, so the
    /// kernels take their fallback paths (a driver bug workaround, and a way to compare paths).
    pub fn global() -> Result<&'static GpuContext> {
        CONTEXT
            .get_or_init(|| Self::create().map_err(|e| e.to_string()))
            .as_ref()
            .map_err(|msg| GearError::NoAdapter(msg.clone()))
    }

    fn create() -> Result<GpuContext> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::PRIMARY;
        let instance = wgpu::Instance::new(desc);
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::PRIMARY));
        let wanted = std::env::var("GEAR_ADAPTER").unwrap_or_default();
        let adapter = choose_adapter(adapters, wanted.trim())?;
        let disabled =
            disabled_features(&std::env::var("GEAR_DISABLE_FEATURES").unwrap_or_default())?;
        let available = adapter.features();
        let mut required = wgpu::Features::empty();
        for (_, optional) in OPTIONAL_FEATURES {
            if available.contains(optional) && !disabled.contains(optional) {
                required |= optional;
            }
        }
        // Ask for everything the adapter can give: large scenes need large storage bindings.
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("gear"),
            required_features: required,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GearError::Gpu(format!("could not open the adapter: {e}")))?;

        let raw = adapter.get_info();
        let info = AdapterInfo {
            name: raw.name.clone(),
            backend: format!("{:?}", raw.backend),
            device_type: format!("{:?}", raw.device_type),
            driver: format!("{} {}", raw.driver, raw.driver_info)
                .trim()
                .to_string(),
            features: OptionalFeatures {
                float32_atomics: required.contains(wgpu::Features::SHADER_FLOAT32_ATOMIC),
                subgroups: required.contains(wgpu::Features::SUBGROUP),
                timestamps: required.contains(wgpu::Features::TIMESTAMP_QUERY),
            },
            max_storage_binding_bytes: limits.max_storage_buffer_binding_size,
            max_workgroups_per_dim: limits.max_compute_workgroups_per_dimension,
            max_storage_buffers_per_stage: limits.max_storage_buffers_per_shader_stage,
        };
        Ok(GpuContext {
            pipelines: PipelineCache::default(),
            buffers: BufferPool::default(),
            device,
            queue,
            info,
        })
    }

    /// Blocks until all submitted work is done; surfaces device errors as [`GearError::Gpu`].
    pub fn wait(&self) -> Result<()> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GearError::Gpu(format!("waiting for the device failed: {e}")))
    }
}

/// The optional features the kernels use when the adapter has them, by their user-facing name.
const OPTIONAL_FEATURES: [(&str, wgpu::Features); 3] = [
    ("float32_atomics", wgpu::Features::SHADER_FLOAT32_ATOMIC),
    ("subgroups", wgpu::Features::SUBGROUP),
    ("timestamps", wgpu::Features::TIMESTAMP_QUERY),
];

/// The features named in `spec` (comma-separated, blanks ignored); an unknown name is an error
/// listing the valid ones, so a typo cannot silently leave a feature on.
fn disabled_features(spec: &str) -> Result<wgpu::Features> {
    let mut disabled = wgpu::Features::empty();
    for name in spec.split(',').map(str::trim).filter(|n| !n.is_empty()) {
        let (_, feature) = OPTIONAL_FEATURES
            .iter()
            .find(|(known, _)| known.eq_ignore_ascii_case(name))
            .ok_or_else(|| {
                let known: Vec<&str> = OPTIONAL_FEATURES.iter().map(|(n, _)| *n).collect();
                GearError::Gpu(format!(
                    "GEAR_DISABLE_FEATURES: unknown feature {name:?}; expected some of {known:?}"
                ))
            })?;
        disabled |= *feature;
    }
    Ok(disabled)
}

fn is_software(info: &wgpu::AdapterInfo) -> bool {
    info.device_type == wgpu::DeviceType::Cpu
}

/// Picks an adapter: forced by `wanted` when given, else the first real GPU, else software.
fn choose_adapter(adapters: Vec<wgpu::Adapter>, wanted: &str) -> Result<wgpu::Adapter> {
    if adapters.is_empty() {
        return Err(GearError::NoAdapter(INSTALL_HINT.into()));
    }
    let names: Vec<String> = adapters.iter().map(|a| a.get_info().name).collect();
    let rank = |a: &wgpu::Adapter| -> Option<u32> {
        let info = a.get_info();
        match wanted.to_ascii_lowercase().as_str() {
            "" => Some(match info.device_type {
                wgpu::DeviceType::DiscreteGpu => 0,
                wgpu::DeviceType::IntegratedGpu => 1,
                wgpu::DeviceType::VirtualGpu => 2,
                wgpu::DeviceType::Other => 3,
                wgpu::DeviceType::Cpu => 4,
            }),
            "cpu" => is_software(&info).then_some(0),
            "gpu" => (!is_software(&info)).then_some(0),
            needle => info.name.to_ascii_lowercase().contains(needle).then_some(0),
        }
    };
    adapters
        .into_iter()
        .filter_map(|a| rank(&a).map(|r| (r, a)))
        .min_by_key(|(r, _)| *r)
        .map(|(_, a)| a)
        .ok_or_else(|| {
            GearError::NoAdapter(format!(
                "GEAR_ADAPTER={wanted:?} matches none of the adapters found: {names:?}"
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disabled_features_parse_names_and_reject_typos() {
        assert_eq!(disabled_features("").unwrap(), wgpu::Features::empty());
        assert_eq!(
            disabled_features(" subgroups , Float32_Atomics,").unwrap(),
            wgpu::Features::SUBGROUP | wgpu::Features::SHADER_FLOAT32_ATOMIC
        );
        let err = disabled_features("subgroup").unwrap_err().to_string();
        assert!(
            err.contains("\"subgroup\"") && err.contains("subgroups"),
            "{err}"
        );
    }
}
