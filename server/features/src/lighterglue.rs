//! Matchers that output a log-assignment matrix (the LightGlue/SuperGlue family) on ONNX Runtime:
//! LighterGlue (LightGlue configured for XFeat) by default, or any model following the same contract
//! (`models/README.md`) with its own descriptor length. The match filter runs here.

use std::path::Path;

use crate::runtime::{OnnxModel, RuntimeOptions};
use crate::xfeat::XFEAT_DIM;
use crate::{FeatureError, Features, Matcher, Matches};

/// A log-assignment matcher (LighterGlue by default).
#[derive(Debug)]
pub struct LighterGlue {
    model: OnnxModel,
    dim: usize,
    name: &'static str,
    /// Minimum match probability (LightGlue's `filter_threshold`). Default 0.1.
    pub threshold: f32,
}

impl LighterGlue {
    /// Load `models/lighterglue.onnx` (64-d XFeat descriptors).
    pub fn load(path: &Path, runtime: &RuntimeOptions) -> Result<Self, FeatureError> {
        Self::load_custom(path, runtime, XFEAT_DIM, "lighterglue")
    }

    /// Load a user-supplied matcher that follows the same contract, for `dim`-long descriptors.
    pub fn load_custom(
        path: &Path,
        runtime: &RuntimeOptions,
        dim: usize,
        name: &'static str,
    ) -> Result<Self, FeatureError> {
        let model = OnnxModel::load(
            path,
            runtime,
            &["kpts0", "kpts1", "desc0", "desc1", "size0", "size1"],
            &["scores"],
        )?;
        Ok(Self {
            model,
            dim,
            name,
            threshold: 0.1,
        })
    }
}

/// Mutual best entries of a log-assignment matrix [m+1, n+1] with probability above `threshold`.
pub fn filter_matches(scores: &[f32], m: usize, n: usize, threshold: f32) -> Matches {
    let w = n + 1;
    let best0: Vec<(usize, f32)> = (0..m)
        .map(|i| {
            (0..n).fold((0, f32::NEG_INFINITY), |acc, j| {
                let s = scores[i * w + j];
                if s > acc.1 {
                    (j, s)
                } else {
                    acc
                }
            })
        })
        .collect();
    let best1: Vec<usize> = (0..n)
        .map(|j| {
            (0..m)
                .fold((0, f32::NEG_INFINITY), |acc, i| {
                    let s = scores[i * w + j];
                    if s > acc.1 {
                        (i, s)
                    } else {
                        acc
                    }
                })
                .0
        })
        .collect();
    let mut out = Matches::default();
    for (i, &(j, s)) in best0.iter().enumerate() {
        let p = s.exp();
        if best1[j] == i && p > threshold {
            out.pairs.push((i as u32, j as u32));
            out.scores.push(p);
        }
    }
    out
}

impl LighterGlue {
    /// The execution provider in use.
    pub fn provider(&self) -> &'static str {
        self.model.provider()
    }
}

impl Matcher for LighterGlue {
    fn match_features(&self, a: &Features, b: &Features) -> Result<Matches, FeatureError> {
        if a.dim != self.dim || b.dim != self.dim {
            return Err(FeatureError::Input(format!(
                "{} takes {}-d descriptors, got {} and {}",
                self.name, self.dim, a.dim, b.dim
            )));
        }
        let (m, n) = (a.len(), b.len());
        if m < 2 || n < 2 {
            return Ok(Matches::default());
        }
        let k0: Vec<f32> = a.keypoints.iter().flatten().copied().collect();
        let k1: Vec<f32> = b.keypoints.iter().flatten().copied().collect();
        let s0 = [a.image_size.0 as f32, a.image_size.1 as f32];
        let s1 = [b.image_size.0 as f32, b.image_size.1 as f32];
        let out = self.model.run(
            &[
                ("kpts0", vec![1, m, 2], &k0),
                ("kpts1", vec![1, n, 2], &k1),
                ("desc0", vec![1, m, self.dim], &a.descriptors),
                ("desc1", vec![1, n, self.dim], &b.descriptors),
                ("size0", vec![1, 2], &s0),
                ("size1", vec![1, 2], &s1),
            ],
            &["scores"],
        )?;
        let (shape, scores) = &out[0];
        if shape != &[1, m + 1, n + 1] {
            return Err(FeatureError::Inference(format!(
                "scores shape {shape:?}, expected [1, {}, {}]",
                m + 1,
                n + 1
            )));
        }
        Ok(filter_matches(scores, m, n, self.threshold))
    }

    fn name(&self) -> &'static str {
        self.name
    }
}
