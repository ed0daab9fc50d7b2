//! Mutual nearest neighbours: cosine similarity on float descriptors, Hamming distance on binary ones
//! (ORB), each with an optional ratio test.

use crate::{FeatureError, Features, Matcher, Matches};

/// MNN settings.
#[derive(Debug, Clone, PartialEq)]
pub struct MnnParams {
    /// Minimum cosine similarity of a match (descriptors are L2-normalised). Default 0.82, XFeat's.
    pub min_similarity: f32,
    /// Lowe's ratio on distances (best < ratio x second best); `None` disables it.
    pub ratio: Option<f32>,
    /// Largest Hamming distance (of 256 bits) of a binary match. Default 64 (ORB-SLAM's strict bound
    /// is 50, its loose one 100).
    pub max_hamming: u32,
}

impl Default for MnnParams {
    fn default() -> Self {
        Self {
            min_similarity: 0.82,
            ratio: None,
            max_hamming: 64,
        }
    }
}

/// Mutual nearest-neighbour matcher.
#[derive(Debug, Clone, Default)]
pub struct Mnn {
    /// Settings.
    pub params: MnnParams,
}

fn hamming(a: &[u8; 32], b: &[u8; 32]) -> u32 {
    a.chunks_exact(8)
        .zip(b.chunks_exact(8))
        .map(|(x, y)| {
            let x = u64::from_le_bytes(x.try_into().expect("8 bytes"));
            let y = u64::from_le_bytes(y.try_into().expect("8 bytes"));
            (x ^ y).count_ones()
        })
        .sum()
}

impl Mnn {
    fn match_binary(&self, a: &Features, b: &Features) -> Matches {
        let (n, m) = (a.binary.len(), b.binary.len());
        let mut out = Matches::default();
        if n == 0 || m == 0 {
            return out;
        }
        let d: Vec<u32> = (0..n * m)
            .map(|k| hamming(&a.binary[k / m], &b.binary[k % m]))
            .collect();
        let best_a: Vec<usize> = (0..m)
            .map(|j| (0..n).min_by_key(|&i| d[i * m + j]).unwrap_or(0))
            .collect();
        for i in 0..n {
            let row = &d[i * m..(i + 1) * m];
            let (mut bj, mut d1, mut d2) = (0, u32::MAX, u32::MAX);
            for (j, &x) in row.iter().enumerate() {
                if x < d1 {
                    d2 = d1;
                    d1 = x;
                    bj = j;
                } else if x < d2 {
                    d2 = x;
                }
            }
            if best_a[bj] != i || d1 > self.params.max_hamming {
                continue;
            }
            if let Some(r) = self.params.ratio {
                if m > 1 && d1 as f32 >= r * d2 as f32 {
                    continue;
                }
            }
            out.pairs.push((i as u32, bj as u32));
            out.scores.push(1.0 - d1 as f32 / 256.0);
        }
        out
    }
}

/// Buffers [`mutual_nearest`] reuses from call to call (the similarity matrix and the best match
/// of every row and column).
#[derive(Debug, Default)]
pub struct MnnBuffers {
    sim: Vec<f32>,
    rows: Vec<(u32, f32, f32)>,
    cols: Vec<(u32, f32)>,
}

/// Mutual nearest neighbours between the rows of `a` and of `b` (unit float descriptors of `dim`
/// values; a partial last row is ignored), by cosine similarity, with `params`' similarity floor and
/// ratio test (`max_hamming` is for binary descriptors and unused here): the pairs and their
/// similarities are appended to `out`. All similarities come from one matrix product (a blocked,
/// vectorised sgemm) into `buf`, then the best match per row (with the second best, for the ratio)
/// and per column in a single row-major pass; the first maximum wins ties. Nothing for `dim == 0`
/// or an empty side.
pub fn mutual_nearest(
    a: &[f32],
    b: &[f32],
    dim: usize,
    params: &MnnParams,
    buf: &mut MnnBuffers,
    out: &mut Matches,
) {
    if dim == 0 {
        return;
    }
    let (n, m) = (a.len() / dim, b.len() / dim);
    if n == 0 || m == 0 {
        return;
    }
    let av = ndarray::ArrayView2::from_shape((n, dim), &a[..n * dim]).expect("n whole rows");
    let bv = ndarray::ArrayView2::from_shape((m, dim), &b[..m * dim]).expect("m whole rows");
    buf.sim.clear();
    buf.sim.resize(n * m, 0.0);
    let mut sim = ndarray::ArrayViewMut2::from_shape((n, m), &mut buf.sim[..]).expect("n x m");
    ndarray::linalg::general_mat_mul(1.0, &av, &bv.t(), 0.0, &mut sim);
    buf.rows.clear();
    buf.cols.clear();
    buf.cols.resize(m, (0, f32::NEG_INFINITY));
    for (i, row) in buf.sim.chunks_exact(m).enumerate() {
        let (mut bj, mut b1, mut b2) = (0, f32::NEG_INFINITY, f32::NEG_INFINITY);
        for (j, (&s, col)) in row.iter().zip(buf.cols.iter_mut()).enumerate() {
            if s > b1 {
                b2 = b1;
                b1 = s;
                bj = j;
            } else if s > b2 {
                b2 = s;
            }
            if s > col.1 {
                *col = (i as u32, s);
            }
        }
        buf.rows.push((bj as u32, b1, b2));
    }
    for (i, &(j, s1, s2)) in buf.rows.iter().enumerate() {
        if buf.cols[j as usize].0 != i as u32 || s1 < params.min_similarity {
            continue;
        }
        if let Some(r) = params.ratio {
            let d1 = (2.0 - 2.0 * s1).max(0.0).sqrt();
            let d2 = (2.0 - 2.0 * s2).max(0.0).sqrt();
            if m > 1 && d1 >= r * d2 {
                continue;
            }
        }
        out.pairs.push((i as u32, j));
        out.scores.push(s1);
    }
}

impl Matcher for Mnn {
    fn match_features(&self, a: &Features, b: &Features) -> Result<Matches, FeatureError> {
        match (a.binary.is_empty(), b.binary.is_empty()) {
            (false, false) => return Ok(self.match_binary(a, b)),
            (true, true) => {}
            _ => {
                return Err(FeatureError::Input(
                    "cannot match binary (ORB) descriptors against float ones".into(),
                ))
            }
        }
        if a.dim != b.dim {
            return Err(FeatureError::Input(format!(
                "descriptor lengths differ: {} vs {}",
                a.dim, b.dim
            )));
        }
        let (n, m) = (a.len(), b.len());
        if a.descriptors.len() != n * a.dim {
            return Err(FeatureError::Input(format!(
                "descriptors of the first set: {} values for {n} keypoints of {}",
                a.descriptors.len(),
                a.dim
            )));
        }
        if b.descriptors.len() != m * b.dim {
            return Err(FeatureError::Input(format!(
                "descriptors of the second set: {} values for {m} keypoints of {}",
                b.descriptors.len(),
                b.dim
            )));
        }
        let mut out = Matches::default();
        mutual_nearest(
            &a.descriptors,
            &b.descriptors,
            a.dim,
            &self.params,
            &mut MnnBuffers::default(),
            &mut out,
        );
        Ok(out)
    }

    fn name(&self) -> &'static str {
        "mnn"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn features(n: usize, dim: usize, seed: u64) -> Features {
        // A small deterministic generator: unit vectors with varied directions.
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        let mut descriptors = Vec::with_capacity(n * dim);
        for _ in 0..n {
            let v: Vec<f32> = (0..dim).map(|_| next()).collect();
            let norm = v.iter().map(|a| a * a).sum::<f32>().sqrt();
            descriptors.extend(v.iter().map(|a| a / norm));
        }
        Features {
            keypoints: vec![[0.0, 0.0]; n],
            scores: vec![1.0; n],
            descriptors,
            dim,
            binary: Vec::new(),
            image_size: (64, 64),
        }
    }

    /// The definition, written the slow way: mutual best by cosine, above the threshold.
    fn reference(a: &Features, b: &Features, min: f32) -> Vec<(u32, u32)> {
        let dot = |i: usize, j: usize| -> f32 {
            a.descriptor(i)
                .iter()
                .zip(b.descriptor(j))
                .map(|(x, y)| x * y)
                .sum()
        };
        let mut out = Vec::new();
        for i in 0..a.len() {
            let j = (0..b.len())
                .max_by(|&p, &q| dot(i, p).total_cmp(&dot(i, q)))
                .unwrap();
            let back = (0..a.len())
                .max_by(|&p, &q| dot(p, j).total_cmp(&dot(q, j)))
                .unwrap();
            if back == i && dot(i, j) >= min {
                out.push((i as u32, j as u32));
            }
        }
        out
    }

    #[test]
    fn matrix_product_mnn_agrees_with_the_definition() {
        // b is a noisy, shuffled copy of part of a, so there are true mutual matches.
        let a = features(300, 64, 1);
        let noise = features(250, 64, 2);
        let mut b = noise.clone();
        for j in 0..250 {
            let i = (j * 7) % 300;
            let mixed: Vec<f32> = a
                .descriptor(i)
                .iter()
                .zip(noise.descriptor(j))
                .map(|(x, y)| x + 0.3 * y)
                .collect();
            let norm = mixed.iter().map(|v| v * v).sum::<f32>().sqrt();
            b.descriptors[j * 64..(j + 1) * 64]
                .iter_mut()
                .zip(&mixed)
                .for_each(|(d, v)| *d = v / norm);
        }
        for min in [0.0, 0.82] {
            let mnn = Mnn {
                params: MnnParams {
                    min_similarity: min,
                    ..MnnParams::default()
                },
            };
            let got = mnn.match_features(&a, &b).unwrap().pairs;
            assert_eq!(got, reference(&a, &b, min), "min similarity {min}");
            assert!(got.len() > 100, "{} matches", got.len());
        }
    }
}
