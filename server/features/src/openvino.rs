//! OpenVINO as a second inference engine for ONNX models on the CPU (the `xfeat-bf16` extractor).
//!
//! Why: on a CPU with AVX-512 BF16 (AMD Zen 4, Intel Cooper Lake and later) OpenVINO's CPU plugin
//! runs XFeat's convolutions in bfloat16 (8-bit mantissa products, f32 accumulation), about 1.9x
//! faster than ONNX Runtime's f32 kernels on one core; XFeat's descriptors stay within a cosine of
//! 0.9999 of the f32 ones (BENCHMARKS.md, "bf16 XFeat on OpenVINO"). Where the CPU has no bf16
//! instructions the plugin runs f32, and [`OvModel::precision`] says so.
//!
//! The C library (`libopenvino_c.so.2641`, with the core, the CPU plugin, the ONNX frontend and TBB
//! beside it) is loaded at run time, found in order: `OPENVINO_DYLIB_PATH`, then
//! `.deps/openvino/libopenvino_c.so.2641` next to the executable's workspace (walking up from the
//! executable) or the current directory, where `scripts/setup.sh` puts it from the openvino wheel.
//! Each model instance compiles its own single-stream executable (one inference at a time, no CPU
//! pinning: a service's workers each run one, and pinned streams of separate instances would share
//! one core).

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use openvino::{CompiledModel, Core, DeviceType, ElementType, InferRequest, RwPropertyKey, Shape};

use crate::runtime::Tensor;
use crate::FeatureError;

/// File name of the OpenVINO C library set-up installs (openvino 2026.4.1).
pub const OPENVINO_LIBRARY: &str = "libopenvino_c.so.2641";

/// Arithmetic the CPU plugin is asked to infer in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    /// IEEE single precision throughout.
    F32,
    /// bfloat16 products where the CPU has the instructions (f32 otherwise).
    Bf16,
}

impl Precision {
    /// The value of OpenVINO's `INFERENCE_PRECISION_HINT`.
    pub fn hint(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
        }
    }
}

/// Whether this CPU has bfloat16 dot-product instructions (AVX-512 BF16: AMD Zen 4 and later,
/// Intel Cooper Lake, Sapphire Rapids and later), with which OpenVINO's CPU plugin runs a
/// [`Precision::Bf16`] model faster than f32 (BENCHMARKS.md, "bf16 XFeat on OpenVINO"). Without
/// them the plugin runs f32, no faster than ONNX Runtime and not to its bit, so a server serves
/// the float backbone there. Always `false` off x86-64.
pub fn cpu_has_bf16() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

static INIT: OnceLock<Result<PathBuf, String>> = OnceLock::new();

/// Load the OpenVINO C library once per process; returns its path. Later calls return the first
/// call's outcome. Errors: the library is in none of the places above, or cannot be loaded (the
/// message names the path).
pub fn init() -> Result<&'static Path, FeatureError> {
    INIT.get_or_init(|| {
        let tried =
            crate::dylib::candidates(None, "OPENVINO_DYLIB_PATH", "openvino", OPENVINO_LIBRARY)?;
        let found = crate::dylib::first_file(&tried, "OPENVINO_DYLIB_PATH")?;
        check_library(found)?;
        openvino_sys::library::load_from(found).map_err(|e| format!("{}: {e}", found.display()))?;
        tracing::info!(library = %found.display(), "OpenVINO loaded");
        Ok(found.clone())
    })
    .as_deref()
    .map_err(|e| FeatureError::OpenVino(e.clone()))
}

/// Whether `path` is OpenVINO's C library: openvino-sys panics on a library without its functions
/// (ONNX Runtime's, say), so the one it checks first is looked up here. Errors: the file cannot be
/// opened as a shared library, or lacks `ov_get_openvino_version`.
#[allow(unsafe_code)]
fn check_library(path: &Path) -> Result<(), String> {
    // SAFETY: opening a shared library runs its initialisers; the file is the one the user or
    // set-up named as OpenVINO's, which is then loaded for real anyway.
    let lib = unsafe { libloading::Library::new(path) }.map_err(|e| {
        format!(
            "{}: cannot be opened as a shared library: {e}",
            path.display()
        )
    })?;
    // SAFETY: only the symbol's presence is checked; it is not called.
    let found = unsafe { lib.get::<unsafe extern "C" fn()>(b"ov_get_openvino_version\0") }.is_ok();
    if !found {
        return Err(format!(
            "{} is not OpenVINO's C library (it has no ov_get_openvino_version); \
             OPENVINO_DYLIB_PATH should name {OPENVINO_LIBRARY} from the openvino {} wheel",
            path.display(),
            "2026.4.1"
        ));
    }
    Ok(())
}

/// One compiled model and its inference request.
struct Compiled {
    request: InferRequest,
    // The request runs the compiled model, which runs on the core's plugin: both live as long.
    _model: CompiledModel,
    _core: Core,
}

/// An ONNX model compiled by OpenVINO's CPU plugin, one inference at a time.
pub struct OvModel {
    compiled: Mutex<Compiled>,
    inputs: Vec<String>,
    outputs: Vec<String>,
    precision: &'static str,
}

impl std::fmt::Debug for OvModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OvModel")
            .field("precision", &self.precision)
            .finish()
    }
}

fn names(
    n: usize,
    at: impl Fn(usize) -> Result<openvino::Node, openvino::InferenceError>,
) -> Result<Vec<String>, String> {
    (0..n)
        .map(|i| {
            at(i)
                .and_then(|node| node.get_name())
                .map_err(|e| e.to_string())
        })
        .collect()
}

impl OvModel {
    /// Read `path` (ONNX) and compile it for the CPU with `threads` inference threads and
    /// `precision`. Errors: the library cannot be loaded ([`init`]), or the file is not a model
    /// OpenVINO can read and compile (the message names the file).
    pub fn load(path: &Path, threads: usize, precision: Precision) -> Result<Self, FeatureError> {
        init()?;
        let err = |message: String| FeatureError::Model {
            path: path.display().to_string(),
            message,
        };
        let file = path
            .to_str()
            .ok_or_else(|| err("path is not UTF-8".into()))?;
        let ov = |e: openvino::InferenceError| e.to_string();
        let build = || -> Result<(Compiled, Vec<String>, Vec<String>, String), String> {
            let mut core = Core::new().map_err(|e| e.to_string())?;
            let cpu = DeviceType::CPU;
            let threads = threads.max(1).to_string();
            core.set_property(&cpu, &RwPropertyKey::InferenceNumThreads, &threads)
                .map_err(ov)?;
            core.set_property(&cpu, &RwPropertyKey::NumStreams, "1")
                .map_err(ov)?;
            core.set_property(&cpu, &RwPropertyKey::HintEnableCpuPinning, "NO")
                .map_err(ov)?;
            core.set_property(
                &cpu,
                &RwPropertyKey::HintInferencePrecision,
                precision.hint(),
            )
            .map_err(ov)?;
            let model = core.read_model_from_file(file, "").map_err(ov)?;
            let inputs = names(model.get_inputs_len().map_err(ov)?, |i| {
                model.get_input_by_index(i)
            })?;
            let outputs = names(model.get_outputs_len().map_err(ov)?, |i| {
                model.get_output_by_index(i)
            })?;
            let mut compiled = core.compile_model(&model, cpu).map_err(ov)?;
            let used = compiled
                .get_property(&openvino::PropertyKey::Rw(
                    RwPropertyKey::HintInferencePrecision,
                ))
                .map_err(ov)?
                .into_owned();
            let request = compiled.create_infer_request().map_err(ov)?;
            Ok((
                Compiled {
                    request,
                    _model: compiled,
                    _core: core,
                },
                inputs,
                outputs,
                used,
            ))
        };
        let (compiled, inputs, outputs, used) =
            build().map_err(|e| err(format!("OpenVINO cannot load it: {e}")))?;
        let precision = if used.eq_ignore_ascii_case("bf16") {
            "bf16"
        } else {
            if precision == Precision::Bf16 {
                tracing::warn!(
                    model = %path.display(),
                    precision = %used,
                    "this CPU has no bfloat16 instructions; OpenVINO infers in f32"
                );
            }
            "f32"
        };
        tracing::info!(model = %path.display(), precision, threads, "OpenVINO compiled the model");
        Ok(Self {
            compiled: Mutex::new(compiled),
            inputs,
            outputs,
            precision,
        })
    }

    /// The model's input names.
    pub fn inputs(&self) -> &[String] {
        &self.inputs
    }

    /// The model's output names.
    pub fn outputs(&self) -> &[String] {
        &self.outputs
    }

    /// The precision the plugin infers in: "bf16" or "f32".
    pub fn precision(&self) -> &'static str {
        self.precision
    }

    /// Run with f32 inputs given as (name, shape, data); returns the named f32 outputs as
    /// (shape, data) in the order asked. Errors: a name the model lacks, a shape its graph
    /// refuses, or a failed inference.
    pub fn run(
        &self,
        inputs: &[(&str, Vec<usize>, &[f32])],
        outputs: &[&str],
    ) -> Result<Vec<Tensor>, String> {
        let ov = |e: openvino::InferenceError| e.to_string();
        let mut c = self
            .compiled
            .lock()
            .map_err(|_| "a previous inference panicked".to_string())?;
        for (name, shape, data) in inputs {
            if shape.iter().product::<usize>() != data.len() {
                return Err(format!(
                    "input `{name}`: {} values for shape {shape:?}",
                    data.len()
                ));
            }
            let dims: Vec<i64> = shape.iter().map(|&d| d as i64).collect();
            let shape = Shape::new(&dims).map_err(ov)?;
            let mut t = openvino::Tensor::new(ElementType::F32, &shape).map_err(ov)?;
            t.get_data_mut::<f32>().map_err(ov)?.copy_from_slice(data);
            c.request.set_tensor(name, &t).map_err(ov)?;
        }
        c.request.infer().map_err(ov)?;
        let mut result = Vec::with_capacity(outputs.len());
        for name in outputs {
            let t = c.request.get_tensor(name).map_err(ov)?;
            let kind = t.get_element_type().map_err(ov)?;
            if kind != ElementType::F32 {
                return Err(format!("output `{name}` holds {kind:?}, not f32"));
            }
            let shape: Vec<usize> = t
                .get_shape()
                .map_err(ov)?
                .get_dimensions()
                .iter()
                .map(|&d| d.max(0) as usize)
                .collect();
            result.push((shape, t.get_data::<f32>().map_err(ov)?.to_vec()));
        }
        Ok(result)
    }
}
