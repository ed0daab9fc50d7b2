//! A user-supplied extractor on ONNX Runtime (SuperPoint, DISK, ... exported elsewhere).
//!
//! Contract (see `models/README.md`): input `image` [1, 3, H, W] float32 RGB in 0..1 at the image's own
//! size; outputs `keypoints` [1, N, 2] float32 pixels (x, y), `scores` [1, N] float32 and
//! `descriptors` [1, N, D] float32. Keypoints with a score of 0 or less are padding and dropped.
//! Descriptors are used as given (normalise them in the model if the matcher expects unit length).
//! A model that needs sizes in multiples of some stride (ALIKED: 32) gets the image resized to the
//! largest such size and its keypoints scaled back to the input's pixels.

use std::path::Path;

use pntr_core::RgbImage;

use crate::runtime::{OnnxModel, RuntimeOptions};
use crate::{Extractor, FeatureError, Features};

/// A generic ONNX extractor.
#[derive(Debug)]
pub struct OnnxExtractor {
    model: OnnxModel,
    top_k: usize,
    multiple_of: Option<usize>,
    name: &'static str,
}

impl OnnxExtractor {
    /// Load a model that follows the contract; keep at most `top_k` keypoints (by score).
    pub fn load(path: &Path, runtime: &RuntimeOptions, top_k: usize) -> Result<Self, FeatureError> {
        Self::load_named(path, runtime, top_k, None, "onnx")
    }

    /// Load a contract-following model under a configuration name, resizing inputs to multiples of
    /// `multiple_of` when given.
    pub fn load_named(
        path: &Path,
        runtime: &RuntimeOptions,
        top_k: usize,
        multiple_of: Option<usize>,
        name: &'static str,
    ) -> Result<Self, FeatureError> {
        let model = OnnxModel::load(
            path,
            runtime,
            &["image"],
            &["keypoints", "scores", "descriptors"],
        )?;
        Ok(Self {
            model,
            top_k,
            multiple_of,
            name,
        })
    }
}

impl Extractor for OnnxExtractor {
    fn extract(&self, image: &RgbImage) -> Result<Features, FeatureError> {
        let (w, h) = (image.width as usize, image.height as usize);
        if w == 0 || h == 0 || image.data.len() != w * h * 3 {
            return Err(FeatureError::Input(format!(
                "RGB buffer of {} bytes for {w}x{h}",
                image.data.len()
            )));
        }
        let (rh, rw) = match self.multiple_of {
            Some(m) if m > 1 => (h / m * m, w / m * m),
            _ => (h, w),
        };
        if rh == 0 || rw == 0 {
            return Err(FeatureError::Input(format!(
                "image {w}x{h} is smaller than the model's stride {}",
                self.multiple_of.unwrap_or(1)
            )));
        }
        let planar = crate::xfeat::planar_rgb(image, rh, rw);
        let (sx, sy) = (w as f32 / rw as f32, h as f32 / rh as f32);
        let out = self.model.run(
            &[("image", vec![1, 3, rh, rw], &planar)],
            &["keypoints", "scores", "descriptors"],
        )?;
        let bad = |what: String| {
            FeatureError::Inference(format!("{}: {what}", self.model.path().display()))
        };
        let (ks, kd) = &out[0];
        let (ss, sd) = &out[1];
        let (ds, dd) = &out[2];
        if ks.len() != 3
            || ks[2] != 2
            || ss.len() != 2
            || ds.len() != 3
            || ks[1] != ss[1]
            || ks[1] != ds[1]
        {
            return Err(bad(format!("output shapes keypoints {ks:?}, scores {ss:?}, descriptors {ds:?} break the contract")));
        }
        let (n, dim) = (ks[1], ds[2]);
        let mut order: Vec<usize> = (0..n).filter(|&i| sd[i] > 0.0).collect();
        order.sort_by(|&a, &b| sd[b].total_cmp(&sd[a]));
        order.truncate(self.top_k);
        let mut f = Features {
            keypoints: Vec::with_capacity(order.len()),
            scores: Vec::with_capacity(order.len()),
            descriptors: Vec::with_capacity(order.len() * dim),
            dim,
            binary: Vec::new(),
            image_size: (image.width, image.height),
        };
        for i in order {
            let (x, y) = (kd[2 * i], kd[2 * i + 1]);
            if !(x.is_finite() && y.is_finite()) {
                return Err(bad(format!("keypoint {i} is not finite")));
            }
            f.keypoints.push([x * sx, y * sy]);
            f.scores.push(sd[i]);
            f.descriptors.extend_from_slice(&dd[i * dim..(i + 1) * dim]);
        }
        Ok(f)
    }

    fn name(&self) -> &'static str {
        self.name
    }

    fn engine(&self) -> &'static str {
        self.model.provider()
    }
}
