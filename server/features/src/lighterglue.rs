//! LighterGlue: LightGlue configured for XFeat, on ONNX Runtime; the match filter runs here.

use std::path::Path;

use crate::runtime::OnnxModel;
use crate::xfeat::XFEAT_DIM;
use crate::{FeatureError, Features, Matcher, Matches};

/// The LighterGlue matcher.
#[derive(Debug)]
pub struct LighterGlue {
    model: OnnxModel,
    /// Minimum match probability (LightGlue's `filter_threshold`). Default 0.1.
    pub threshold: f32,
}

impl LighterGlue {
    /// Load `models/lighterglue.onnx`.
    pub fn load(path: &Path, threads: usize) -> Result<Self, FeatureError> {
        let model = OnnxModel::load(
            path,
            threads,
            &["kpts0", "kpts1", "desc0", "desc1", "size0", "size1"],
            &["scores"],
        )?;
        Ok(Self {
            model,
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

impl Matcher for LighterGlue {
    fn match_features(&self, a: &Features, b: &Features) -> Result<Matches, FeatureError> {
        if a.dim != XFEAT_DIM || b.dim != XFEAT_DIM {
            return Err(FeatureError::Input(format!(
                "LighterGlue takes {XFEAT_DIM}-d XFeat descriptors, got {} and {}",
                a.dim, b.dim
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
                ("desc0", vec![1, m, XFEAT_DIM], &a.descriptors),
                ("desc1", vec![1, n, XFEAT_DIM], &b.descriptors),
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
        "lighterglue"
    }
}
