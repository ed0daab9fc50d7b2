//! Mutual nearest neighbours on float descriptors, with an optional ratio test.

use crate::{FeatureError, Features, Matcher, Matches};

/// MNN settings.
#[derive(Debug, Clone, PartialEq)]
pub struct MnnParams {
    /// Minimum cosine similarity of a match (descriptors are L2-normalised). Default 0.82, XFeat's.
    pub min_similarity: f32,
    /// Lowe's ratio on distances (best < ratio x second best); `None` disables it.
    pub ratio: Option<f32>,
}

impl Default for MnnParams {
    fn default() -> Self {
        Self {
            min_similarity: 0.82,
            ratio: None,
        }
    }
}

/// Mutual nearest-neighbour matcher.
#[derive(Debug, Clone, Default)]
pub struct Mnn {
    /// Settings.
    pub params: MnnParams,
}

impl Matcher for Mnn {
    fn match_features(&self, a: &Features, b: &Features) -> Result<Matches, FeatureError> {
        if a.dim != b.dim {
            return Err(FeatureError::Input(format!(
                "descriptor lengths differ: {} vs {}",
                a.dim, b.dim
            )));
        }
        let (n, m) = (a.len(), b.len());
        if n == 0 || m == 0 {
            return Ok(Matches::default());
        }
        let mut sim = vec![0f32; n * m];
        for i in 0..n {
            let da = a.descriptor(i);
            for j in 0..m {
                sim[i * m + j] = da.iter().zip(b.descriptor(j)).map(|(x, y)| x * y).sum();
            }
        }
        let best_b: Vec<(usize, f32, f32)> = (0..n)
            .map(|i| {
                let row = &sim[i * m..(i + 1) * m];
                let (mut bj, mut b1, mut b2) = (0, f32::NEG_INFINITY, f32::NEG_INFINITY);
                for (j, &s) in row.iter().enumerate() {
                    if s > b1 {
                        b2 = b1;
                        b1 = s;
                        bj = j;
                    } else if s > b2 {
                        b2 = s;
                    }
                }
                (bj, b1, b2)
            })
            .collect();
        let best_a: Vec<usize> = (0..m)
            .map(|j| {
                (0..n)
                    .max_by(|&x, &y| sim[x * m + j].total_cmp(&sim[y * m + j]))
                    .unwrap_or(0)
            })
            .collect();
        let mut out = Matches::default();
        for (i, &(j, s1, s2)) in best_b.iter().enumerate() {
            if best_a[j] != i || s1 < self.params.min_similarity {
                continue;
            }
            if let Some(r) = self.params.ratio {
                let d1 = (2.0 - 2.0 * s1).max(0.0).sqrt();
                let d2 = (2.0 - 2.0 * s2).max(0.0).sqrt();
                if m > 1 && d1 >= r * d2 {
                    continue;
                }
            }
            out.pairs.push((i as u32, j as u32));
            out.scores.push(s1);
        }
        Ok(out)
    }

    fn name(&self) -> &'static str {
        "mnn"
    }
}
