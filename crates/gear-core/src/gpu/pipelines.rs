//! Compiled compute pipelines, cached per (shader, specialisation).
//!
//! Specialisation is done in the source: constants are prepended as `const NAME: T = v;` lines,
//! so that they can size arrays and let the compiler drop dead branches (a render that needs
//! no depth compiles no depth code). Each distinct option set compiles once per process.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// A shader plus the constants it is specialised with.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct ShaderSpec {
    pub name: &'static str,
    pub source: &'static str,
    pub entry: &'static str,
    /// `(name, wgsl literal)` pairs, e.g. `("CHANNELS", "11u")`, `("WITH_DEPTH", "true")`.
    pub constants: Vec<(&'static str, String)>,
}

impl ShaderSpec {
    pub fn new(name: &'static str, source: &'static str, entry: &'static str) -> Self {
        Self {
            name,
            source,
            entry,
            constants: Vec::new(),
        }
    }

    pub fn with(mut self, name: &'static str, value: impl ToString) -> Self {
        self.constants.push((name, value.to_string()));
        self
    }

    /// The WGSL text actually compiled: the constants, then the shader.
    pub fn specialised_source(&self) -> String {
        let mut out = String::new();
        for (name, value) in &self.constants {
            out.push_str(&format!("const {name} = {value};\n"));
        }
        out.push_str(self.source);
        out
    }
}

#[derive(Default)]
pub struct PipelineCache {
    pipelines: Mutex<HashMap<ShaderSpec, Arc<wgpu::ComputePipeline>>>,
}

impl PipelineCache {
    /// The pipeline for `spec`, compiled on first request (layout inferred from the shader).
    pub fn get(&self, device: &wgpu::Device, spec: &ShaderSpec) -> Arc<wgpu::ComputePipeline> {
        let mut map = self.pipelines.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = map.get(spec) {
            return p.clone();
        }
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(spec.name),
            source: wgpu::ShaderSource::Wgsl(spec.specialised_source().into()),
        });
        let pipeline = Arc::new(
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(spec.name),
                layout: None,
                module: &module,
                entry_point: Some(spec.entry),
                compilation_options: Default::default(),
                cache: None,
            }),
        );
        map.insert(spec.clone(), pipeline.clone());
        pipeline
    }

    pub fn len(&self) -> usize {
        self.pipelines.lock().map(|m| m.len()).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}
