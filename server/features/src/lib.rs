//! Local features: keypoints and descriptors from an image, and matches between two sets.
//!
//! Learned models run on ONNX Runtime through `ort` with the library loaded at run time
//! ([`runtime`]), so the build never downloads anything and the same binary uses the CPU library from
//! set-up or a GPU build of ONNX Runtime when one is installed; OpenVINO, loaded the same way
//! ([`openvino`]), runs XFeat's backbone in bfloat16 for the `xfeat-bf16` extractor. Models are plain graphs with documented
//! contracts (`models/README.md`): XFeat's CNN exports as dense maps and its sparse step (NMS, top-k,
//! descriptor sampling) runs here in Rust, which keeps the graph exportable at any image size; the
//! LighterGlue graph returns the log assignment and the match filter runs here.
//!
//! Output keeps pairs aligned: a [`Matches`] holds indices into both keypoint lists and a score.

pub mod config;
mod dylib;
pub mod lighterglue;
pub mod mnn;
pub mod models_dir;
pub mod onnx_extractor;
pub mod openvino;
pub mod orb;
pub mod runtime;
pub mod xfeat;

use pntr_core::RgbImage;

/// Errors of feature extraction and matching.
#[derive(Debug, thiserror::Error)]
pub enum FeatureError {
    /// ONNX Runtime could not be loaded or initialised.
    #[error("ONNX Runtime: {0}")]
    Runtime(String),
    /// OpenVINO (the `xfeat-bf16` extractor's engine) could not be loaded.
    #[error("OpenVINO: {0}")]
    OpenVino(String),
    /// A model file is missing or unreadable, or does not follow its contract.
    #[error("model {path}: {message}")]
    Model {
        /// The model file.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// An input cannot be processed (wrong size, empty, mismatched dimensions).
    #[error("invalid input: {0}")]
    Input(String),
    /// Inference failed.
    #[error("inference failed: {0}")]
    Inference(String),
}

/// Keypoints with descriptors of one image.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Features {
    /// Keypoints (x = column, y = row) in pixels of the input image, OpenCV convention.
    pub keypoints: Vec<[f32; 2]>,
    /// Detection score per keypoint.
    pub scores: Vec<f32>,
    /// Float descriptors, `keypoints.len() * dim` values, row-major (empty for binary extractors).
    pub descriptors: Vec<f32>,
    /// Float descriptor length (0 for binary extractors).
    pub dim: usize,
    /// 256-bit binary descriptors, one per keypoint (ORB); empty for float extractors.
    pub binary: Vec<[u8; 32]>,
    /// (width, height) of the image the keypoints refer to.
    pub image_size: (u32, u32),
}

impl Features {
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// True when there are no keypoints.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }

    /// Descriptor of keypoint `i`.
    pub fn descriptor(&self, i: usize) -> &[f32] {
        &self.descriptors[i * self.dim..(i + 1) * self.dim]
    }

    /// Keep the `n` keypoints of highest score (ties: the earlier one), in their order; nothing
    /// changes when there are at most `n`.
    pub fn keep_strongest(&mut self, n: usize) {
        if self.len() <= n {
            return;
        }
        let mut order: Vec<usize> = (0..self.len()).collect();
        order.sort_by(|&a, &b| self.scores[b].total_cmp(&self.scores[a]).then(a.cmp(&b)));
        order.truncate(n);
        order.sort_unstable();
        self.keypoints = order.iter().map(|&i| self.keypoints[i]).collect();
        self.scores = order.iter().map(|&i| self.scores[i]).collect();
        if self.dim > 0 {
            self.descriptors = order
                .iter()
                .flat_map(|&i| self.descriptor(i).to_vec())
                .collect();
        }
        if !self.binary.is_empty() {
            self.binary = order.iter().map(|&i| self.binary[i]).collect();
        }
    }
}

/// Matches between two feature sets: `pairs[k] = (index in the first, index in the second)`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Matches {
    /// Aligned index pairs.
    pub pairs: Vec<(u32, u32)>,
    /// Score of each pair (higher is better; matcher-specific scale in 0..1).
    pub scores: Vec<f32>,
}

/// Something that turns an image into features.
pub trait Extractor: Send + Sync {
    /// Extract features from an RGB image (at most the extractor's configured `top_k`).
    fn extract(&self, image: &RgbImage) -> Result<Features, FeatureError>;
    /// Extract at most `top_k` keypoints, the strongest: what a pipeline calls when the count
    /// depends on the image's size (`pntr_pipeline::preset::Preset::keypoints_for`). No more than
    /// the configured `top_k` come back. The default extracts and keeps the strongest
    /// ([`Features::keep_strongest`]); XFeat selects them in its own top-k step.
    fn extract_at_most(&self, image: &RgbImage, top_k: usize) -> Result<Features, FeatureError> {
        let mut f = self.extract(image)?;
        f.keep_strongest(top_k);
        Ok(f)
    }
    /// The name used in configuration.
    fn name(&self) -> &'static str;
    /// Where its network runs: `cpu` or `cuda` (ONNX Runtime), `openvino-bf16` or `openvino-f32`
    /// (OpenVINO, the precision it infers in on this CPU), `native` for an extractor without a
    /// network (ORB).
    fn engine(&self) -> &'static str {
        "native"
    }
}

/// Something that matches two feature sets.
pub trait Matcher: Send + Sync {
    /// Match `a` against `b`.
    fn match_features(&self, a: &Features, b: &Features) -> Result<Matches, FeatureError>;
    /// The name used in configuration.
    fn name(&self) -> &'static str;
}
