//! Loading ONNX Runtime and models.
//!
//! The shared library is found, in order: an explicit path, `ORT_DYLIB_PATH`, then
//! `.deps/onnxruntime/libonnxruntime.so.1.31.1` next to the executable's workspace (walking up from
//! the executable) or the current directory. Binaries therefore work without extra environment after
//! `scripts/setup.sh`. Sessions are created once; `ort` sessions need `&mut` to run, so each model holds
//! its session behind a mutex (one inference at a time per model instance; a pool of instances gives
//! parallelism).

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;

use crate::openvino::{OvModel, Precision};
use crate::FeatureError;

/// File name of the ONNX Runtime library set-up installs.
pub const ORT_LIBRARY: &str = "libonnxruntime.so.1.31.1";

static INIT: OnceLock<Result<(PathBuf, ort::environment::Environment), String>> = OnceLock::new();

/// Load ONNX Runtime once per process and return the library path and the environment. Later calls
/// return the first call's outcome.
pub fn init(
    explicit: Option<&Path>,
) -> Result<&'static (PathBuf, ort::environment::Environment), FeatureError> {
    INIT.get_or_init(|| {
        let tried =
            crate::dylib::candidates(explicit, "ORT_DYLIB_PATH", "onnxruntime", ORT_LIBRARY)?;
        let found = crate::dylib::first_file(&tried, "ORT_DYLIB_PATH")?;
        let env = ort::init_from(found)
            .map_err(|e| format!("{}: {e}", found.display()))?
            .with_name("pntr")
            .build()
            .map_err(|e| format!("{}: {e}", found.display()))?;
        tracing::info!(library = %found.display(), "ONNX Runtime loaded");
        Ok((found.clone(), env))
    })
    .as_ref()
    .map_err(|e| FeatureError::Runtime(e.clone()))
}

/// Where inference runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Device {
    /// The CPU execution provider.
    #[default]
    Cpu,
    /// The CUDA execution provider on this GPU (needs the `cuda` feature and a GPU build of ONNX
    /// Runtime); falls back to the CPU with a warning when it cannot be registered.
    Cuda(i32),
}

/// Which library runs the models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Engine {
    /// ONNX Runtime, on [`RuntimeOptions::device`].
    #[default]
    OnnxRuntime,
    /// OpenVINO's CPU plugin at this precision ([`crate::openvino`]); `device` is not used.
    OpenVino(Precision),
}

/// How models are run.
#[derive(Debug, Clone, PartialEq)]
pub struct RuntimeOptions {
    /// Intra-op threads per model instance. Default 1: a service gets its parallelism from requests.
    pub threads: usize,
    /// Execution provider.
    pub device: Device,
    /// The inference library.
    pub engine: Engine,
}

impl Default for RuntimeOptions {
    fn default() -> Self {
        Self {
            threads: 1,
            device: Device::Cpu,
            engine: Engine::OnnxRuntime,
        }
    }
}

#[cfg(feature = "cuda")]
fn register_device(b: &mut ort::session::builder::SessionBuilder, device: Device) -> &'static str {
    use ort::ep::ExecutionProvider;
    match device {
        Device::Cpu => "cpu",
        Device::Cuda(id) => match ort::ep::CUDA::default().with_device_id(id).register(b) {
            Ok(()) => {
                tracing::info!(device = id, "CUDA execution provider registered");
                "cuda"
            }
            Err(e) => {
                tracing::warn!(error = %e, "CUDA execution provider unavailable; running on the CPU");
                "cpu"
            }
        },
    }
}

#[cfg(not(feature = "cuda"))]
fn register_device(_b: &mut ort::session::builder::SessionBuilder, device: Device) -> &'static str {
    if let Device::Cuda(_) = device {
        tracing::warn!("built without the `cuda` feature; running on the CPU");
    }
    "cpu"
}

/// An output tensor: shape and row-major data.
pub type Tensor = (Vec<usize>, Vec<f32>);

/// The library a loaded model runs in.
enum Loaded {
    Ort(Mutex<Session>),
    OpenVino(OvModel),
}

/// A loaded model whose input and output names were checked against its contract.
pub struct OnnxModel {
    path: PathBuf,
    loaded: Loaded,
    provider: &'static str,
}

impl std::fmt::Debug for OnnxModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxModel")
            .field("path", &self.path)
            .finish()
    }
}

impl OnnxModel {
    /// Load `path` and check its input and output names against the contract.
    pub fn load(
        path: &Path,
        opts: &RuntimeOptions,
        inputs: &[&str],
        outputs: &[&str],
    ) -> Result<Self, FeatureError> {
        Self::load_layout(path, opts, &[(inputs, outputs)]).map(|(m, _)| m)
    }

    /// Load `path` and find the first of `layouts` (each the input and the output names a graph
    /// of one version of a model has) that the model follows; returns the model and that layout's
    /// index. Errors: the file is missing or not a model ONNX Runtime can load, or the model has
    /// none of the layouts (the message names what each one lacks).
    pub fn load_layout(
        path: &Path,
        opts: &RuntimeOptions,
        layouts: &[(&[&str], &[&str])],
    ) -> Result<(Self, usize), FeatureError> {
        let err = |message: String| FeatureError::Model {
            path: path.display().to_string(),
            message,
        };
        if !path.is_file() {
            return Err(err("file not found".into()));
        }
        let mut provider = "cpu";
        let (loaded, have_in, have_out) = match opts.engine {
            Engine::OnnxRuntime => {
                let (_, env) = init(None)?;
                let mut build = || -> Result<Session, String> {
                    let mut b = Session::builder(env)
                        .map_err(|e| e.to_string())?
                        .with_optimization_level(GraphOptimizationLevel::Level3)
                        .map_err(|e| e.to_string())?
                        .with_intra_threads(opts.threads.max(1))
                        .map_err(|e| e.to_string())?;
                    provider = register_device(&mut b, opts.device);
                    b.commit_from_file(path).map_err(|e| e.to_string())
                };
                let session = build().map_err(|e| err(format!("cannot load: {e}")))?;
                let have_in: Vec<String> = session
                    .inputs()
                    .iter()
                    .map(|o| o.name().to_string())
                    .collect();
                let have_out: Vec<String> = session
                    .outputs()
                    .iter()
                    .map(|o| o.name().to_string())
                    .collect();
                (Loaded::Ort(Mutex::new(session)), have_in, have_out)
            }
            Engine::OpenVino(precision) => {
                if let Device::Cuda(id) = opts.device {
                    tracing::warn!(
                        model = %path.display(),
                        device = id,
                        "OpenVINO runs this model on the CPU; the CUDA device is for ONNX Runtime's models"
                    );
                }
                let m = OvModel::load(path, opts.threads, precision)?;
                provider = match m.precision() {
                    "bf16" => "openvino-bf16",
                    _ => "openvino-f32",
                };
                let (i, o) = (m.inputs().to_vec(), m.outputs().to_vec());
                (Loaded::OpenVino(m), i, o)
            }
        };
        let have_in: Vec<&str> = have_in.iter().map(String::as_str).collect();
        let have_out: Vec<&str> = have_out.iter().map(String::as_str).collect();
        // What the layout lacks, if anything.
        let lacks = |inputs: &[&str], outputs: &[&str]| -> Option<String> {
            for (kind, want, have) in [("input", inputs, &have_in), ("output", outputs, &have_out)]
            {
                if let Some(w) = want.iter().find(|w| !have.contains(w)) {
                    return Some(format!(
                        "has no {kind} `{w}` (its {kind}s: {})",
                        have.join(", ")
                    ));
                }
            }
            None
        };
        let mut lacking = Vec::new();
        let mut found = None;
        for (i, (inputs, outputs)) in layouts.iter().enumerate() {
            match lacks(inputs, outputs) {
                None => {
                    found = Some(i);
                    break;
                }
                Some(why) => lacking.push(why),
            }
        }
        let Some(layout) = found else {
            // One layout: its gap; several: each layout's, so a model of the second layout with one
            // name wrong is not told what the first lacks.
            return Err(err(match lacking.len() {
                0 => "no layout to check".into(),
                1 => lacking.remove(0),
                _ => lacking
                    .iter()
                    .enumerate()
                    .map(|(i, why)| format!("as layout {}: {why}", i + 1))
                    .collect::<Vec<_>>()
                    .join("; "),
            }));
        };
        Ok((
            Self {
                path: path.to_path_buf(),
                loaded,
                provider,
            },
            layout,
        ))
    }

    /// The execution provider in use: "cpu" or "cuda" (ONNX Runtime), "openvino-bf16" or
    /// "openvino-f32" (OpenVINO, the precision it infers in on this CPU).
    pub fn provider(&self) -> &'static str {
        self.provider
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Run with f32 inputs given as (name, shape, data); returns the named f32 outputs as
    /// (shape, data) in the order asked.
    pub fn run(
        &self,
        inputs: &[(&str, Vec<usize>, &[f32])],
        outputs: &[&str],
    ) -> Result<Vec<Tensor>, FeatureError> {
        let session = match &self.loaded {
            Loaded::Ort(session) => session,
            Loaded::OpenVino(m) => {
                return m
                    .run(inputs, outputs)
                    .map_err(|e| FeatureError::Inference(format!("{}: {e}", self.path.display())))
            }
        };
        let inf = |e: ort::Error| FeatureError::Inference(format!("{}: {e}", self.path.display()));
        let mut values = Vec::with_capacity(inputs.len());
        for (name, shape, data) in inputs {
            let t = ort::value::TensorRef::from_array_view((shape.clone(), *data)).map_err(inf)?;
            values.push((
                std::borrow::Cow::Borrowed(*name),
                ort::session::SessionInputValue::from(t),
            ));
        }
        let mut session = session
            .lock()
            .map_err(|_| FeatureError::Inference("a previous inference panicked".into()))?;
        let out = session.run(values).map_err(inf)?;
        let mut result = Vec::with_capacity(outputs.len());
        for name in outputs {
            let (shape, data) = out[*name].try_extract_tensor::<f32>().map_err(inf)?;
            let shape: Vec<usize> = shape.iter().map(|&d| d.max(0) as usize).collect();
            result.push((shape, data.to_vec()));
        }
        Ok(result)
    }
}
