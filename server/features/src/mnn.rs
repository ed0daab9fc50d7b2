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
    /// Best similarity of every column so far, and its row.
    col_best: Vec<f32>,
    col_row: Vec<u32>,
}

/// Lanes of the row-major pass: eight independent running maxima per row (one AVX register of
/// f32), so the pass carries no branch from element to element.
const LANES: usize = 8;

/// Per-lane best, second best and best column of the first `body` elements of a row (a multiple
/// of [`LANES`]), with the columns' best values and rows updated.
type Lanes = ([f32; LANES], [f32; LANES], [u32; LANES]);

/// The lane pass in plain Rust (any target).
fn lanes_portable(row: &[f32], i: u32, col_best: &mut [f32], col_row: &mut [u32]) -> Lanes {
    let mut b1 = [f32::NEG_INFINITY; LANES];
    let mut b2 = [f32::NEG_INFINITY; LANES];
    let mut j1 = [0u32; LANES];
    let lanes = row
        .chunks_exact(LANES)
        .zip(col_best.chunks_exact_mut(LANES))
        .zip(col_row.chunks_exact_mut(LANES));
    for (c, ((s8, cb), cr)) in lanes.enumerate() {
        for l in 0..LANES {
            let s = s8[l];
            // The new second best is the larger of the old one and min(s, best), whichever way s goes.
            let low = if s < b1[l] { s } else { b1[l] };
            b2[l] = if low > b2[l] { low } else { b2[l] };
            if s > b1[l] {
                b1[l] = s;
                j1[l] = (c * LANES + l) as u32;
            }
            if s > cb[l] {
                cb[l] = s;
                cr[l] = i;
            }
        }
    }
    (b1, b2, j1)
}

/// The lane pass with AVX2 (compare, blend), chosen at run time where the CPU has it: about 4x
/// the portable pass, which the compiler leaves scalar (benches/mnn.rs).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod avx2 {
    use super::{Lanes, LANES};
    use std::arch::x86_64::*;

    /// Whether this CPU runs [`lanes`].
    pub fn available() -> bool {
        std::is_x86_feature_detected!("avx2")
    }

    /// [`super::lanes_portable`] on AVX2. Panics unless `col_best` and `col_row` are as long as
    /// `row` and `row`'s length is a multiple of [`LANES`]; call only where [`available`].
    pub fn lanes(row: &[f32], i: u32, col_best: &mut [f32], col_row: &mut [u32]) -> Lanes {
        assert!(available(), "AVX2 pass called on a CPU without AVX2");
        assert!(
            row.len() % LANES == 0 && col_best.len() == row.len() && col_row.len() == row.len()
        );
        // SAFETY: AVX2 is present (checked above); every load and store below is at j..j + 8 with
        // j + 8 <= row.len(), the length of all three slices (checked above).
        unsafe { lanes_avx2(row, i, col_best, col_row) }
    }

    #[target_feature(enable = "avx2")]
    unsafe fn lanes_avx2(row: &[f32], i: u32, col_best: &mut [f32], col_row: &mut [u32]) -> Lanes {
        let mut b1 = _mm256_set1_ps(f32::NEG_INFINITY);
        let mut b2 = b1;
        let mut j1 = _mm256_setzero_si256();
        let mut jv = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let step = _mm256_set1_epi32(LANES as i32);
        let iv = _mm256_set1_epi32(i as i32);
        let mut j = 0;
        while j < row.len() {
            let s = _mm256_loadu_ps(row.as_ptr().add(j));
            // min_ps(a, b) = a < b ? a : b, max_ps(a, b) = a > b ? a : b: the portable selects.
            b2 = _mm256_max_ps(_mm256_min_ps(s, b1), b2);
            let up = _mm256_cmp_ps::<_CMP_GT_OQ>(s, b1);
            j1 = _mm256_blendv_epi8(j1, jv, _mm256_castps_si256(up));
            b1 = _mm256_blendv_ps(b1, s, up);
            let cb = col_best.as_mut_ptr().add(j);
            let cr = col_row.as_mut_ptr().add(j) as *mut __m256i;
            let c = _mm256_loadu_ps(cb);
            let cu = _mm256_cmp_ps::<_CMP_GT_OQ>(s, c);
            _mm256_storeu_ps(cb, _mm256_blendv_ps(c, s, cu));
            let r = _mm256_loadu_si256(cr);
            _mm256_storeu_si256(cr, _mm256_blendv_epi8(r, iv, _mm256_castps_si256(cu)));
            jv = _mm256_add_epi32(jv, step);
            j += LANES;
        }
        let (mut o1, mut o2, mut oj) = ([0f32; LANES], [0f32; LANES], [0u32; LANES]);
        _mm256_storeu_ps(o1.as_mut_ptr(), b1);
        _mm256_storeu_ps(o2.as_mut_ptr(), b2);
        _mm256_storeu_si256(oj.as_mut_ptr() as *mut __m256i, j1);
        (o1, o2, oj)
    }
}

/// The best (with its column, the first among equals) and second-best value of `row`, and every
/// column's best so far (`col_best`, `col_row`, as long as `row`) updated with row `i`: one pass
/// in [`LANES`] lanes (AVX2 where the CPU has it), then the tail and the lanes reduced.
fn scan_row(row: &[f32], i: u32, col_best: &mut [f32], col_row: &mut [u32]) -> (u32, f32, f32) {
    let body = row.len() - row.len() % LANES;
    let (head, tail) = row.split_at(body);
    let (cb_head, cb_tail) = col_best.split_at_mut(body);
    let (cr_head, cr_tail) = col_row.split_at_mut(body);
    #[cfg(target_arch = "x86_64")]
    let (mut b1, mut b2, mut j1) = if avx2::available() {
        avx2::lanes(head, i, cb_head, cr_head)
    } else {
        lanes_portable(head, i, cb_head, cr_head)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let (mut b1, mut b2, mut j1) = lanes_portable(head, i, cb_head, cr_head);
    for (l, ((&s, cb), cr)) in tail.iter().zip(cb_tail).zip(cr_tail).enumerate() {
        if s > b1[l] {
            b2[l] = b1[l];
            b1[l] = s;
            j1[l] = (body + l) as u32;
        } else if s > b2[l] {
            b2[l] = s;
        }
        if s > *cb {
            *cb = s;
            *cr = i;
        }
    }
    // The winning lane: the highest best, the lowest column among equals (the row's first maximum).
    let mut w = 0;
    for l in 1..LANES {
        if b1[l] > b1[w] || (b1[l] == b1[w] && j1[l] < j1[w]) {
            w = l;
        }
    }
    let second = (0..LANES)
        .map(|l| if l == w { b2[l] } else { b1[l] })
        .fold(f32::NEG_INFINITY, |a, b| if b > a { b } else { a });
    (j1[w], b1[w], second)
}

/// Mutual nearest neighbours between the rows of `a` and of `b` (unit float descriptors of `dim`
/// values; a partial last row is ignored), by cosine similarity, with `params`' similarity floor and
/// ratio test (`max_hamming` is for binary descriptors and unused here): the pairs and their
/// similarities are appended to `out`. All similarities come from one matrix product (a blocked,
/// vectorised sgemm) into `buf`, then the best match per row (with the second best, for the ratio)
/// and per column in a single row-major pass of eight lanes (AVX2 where the CPU has it; the pass
/// costs about a third of the product at 1024 x 1024, `benches/mnn.rs`); the first maximum wins
/// ties. Nothing for `dim == 0` or an empty side.
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
    // Grown, never cleared: with beta = 0 the product writes every entry without reading it
    // (matrixmultiply's contract), so stale values from the last call are harmless.
    if buf.sim.len() < n * m {
        buf.sim.resize(n * m, 0.0);
    }
    let mut sim = ndarray::ArrayViewMut2::from_shape((n, m), &mut buf.sim[..n * m]).expect("n x m");
    ndarray::linalg::general_mat_mul(1.0, &av, &bv.t(), 0.0, &mut sim);
    buf.rows.clear();
    buf.col_best.clear();
    buf.col_best.resize(m, f32::NEG_INFINITY);
    buf.col_row.clear();
    buf.col_row.resize(m, 0);
    for (i, row) in buf.sim[..n * m].chunks_exact(m).enumerate() {
        let best = scan_row(row, i as u32, &mut buf.col_best, &mut buf.col_row);
        buf.rows.push(best);
    }
    for (i, &(j, s1, s2)) in buf.rows.iter().enumerate() {
        if buf.col_row[j as usize] != i as u32 || s1 < params.min_similarity {
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

/// Largest similarity matrix (entries) a thread keeps between calls of [`Mnn::match_features`]:
/// 1024 x 1024 keypoints, 4 MiB; larger ones get a buffer of their own.
const REUSED_SIMILARITIES: usize = 1 << 20;

thread_local! {
    /// Each thread's buffers for [`Mnn::match_features`] (a server worker matches five candidates a
    /// frame: one allocation and one clearing of the matrix fewer per match).
    static REUSED: std::cell::RefCell<MnnBuffers> = std::cell::RefCell::new(MnnBuffers::default());
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
        let run = |buf: &mut MnnBuffers, out: &mut Matches| {
            mutual_nearest(
                &a.descriptors,
                &b.descriptors,
                a.dim,
                &self.params,
                buf,
                out,
            )
        };
        if n * m <= REUSED_SIMILARITIES {
            REUSED.with(|buf| run(&mut buf.borrow_mut(), &mut out));
        } else {
            run(&mut MnnBuffers::default(), &mut out);
        }
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

    /// The row pass written plainly: first maximum, second best, column maxima with the first row.
    fn scan_row_plain(row: &[f32], i: u32, cb: &mut [f32], cr: &mut [u32]) -> (u32, f32, f32) {
        let (mut bj, mut b1, mut b2) = (0, f32::NEG_INFINITY, f32::NEG_INFINITY);
        for (j, &s) in row.iter().enumerate() {
            if s > b1 {
                b2 = b1;
                b1 = s;
                bj = j as u32;
            } else if s > b2 {
                b2 = s;
            }
            if s > cb[j] {
                cb[j] = s;
                cr[j] = i;
            }
        }
        (bj, b1, b2)
    }

    #[test]
    fn the_lane_pass_equals_the_plain_pass_ties_and_tails_included() {
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        for m in [1usize, 2, 7, 8, 9, 15, 16, 17, 63, 1027] {
            for levels in [3u64, 50, 1 << 20] {
                // Values on a few levels, so equal maxima in one lane, across lanes and in the tail.
                let rows: Vec<Vec<f32>> = (0..12)
                    .map(|_| {
                        (0..m)
                            .map(|_| (next() % levels) as f32 / levels as f32)
                            .collect()
                    })
                    .collect();
                let (mut cb, mut cr) = (vec![f32::NEG_INFINITY; m], vec![0u32; m]);
                let (mut pb, mut pr) = (cb.clone(), cr.clone());
                for (i, row) in rows.iter().enumerate() {
                    let got = scan_row(row, i as u32, &mut cb, &mut cr);
                    let body = m - m % LANES;
                    let (mut qb, mut qr) = (pb.clone(), pr.clone());
                    let portable =
                        lanes_portable(&row[..body], i as u32, &mut qb[..body], &mut qr[..body]);
                    #[cfg(target_arch = "x86_64")]
                    if avx2::available() {
                        let (mut vb, mut vr) = (pb.clone(), pr.clone());
                        let simd =
                            avx2::lanes(&row[..body], i as u32, &mut vb[..body], &mut vr[..body]);
                        assert_eq!(simd, portable, "AVX2 lanes, m {m}, row {i}");
                        assert_eq!((vb, vr), (qb, qr), "AVX2 columns, m {m}, row {i}");
                    }
                    let want = scan_row_plain(row, i as u32, &mut pb, &mut pr);
                    assert_eq!(got, want, "m {m}, {levels} levels, row {i}");
                }
                assert_eq!((cb, cr), (pb, pr), "columns, m {m}, {levels} levels");
            }
        }
    }

    #[test]
    fn reused_buffers_give_what_fresh_ones_give() {
        let (a, b) = (features(300, 64, 3), features(280, 64, 4));
        let (small_a, small_b) = (features(40, 64, 5), features(90, 64, 6));
        let p = MnnParams {
            min_similarity: 0.0,
            ratio: Some(0.95),
            ..MnnParams::default()
        };
        let run = |x: &Features, y: &Features, buf: &mut MnnBuffers| {
            let mut out = Matches::default();
            mutual_nearest(&x.descriptors, &y.descriptors, 64, &p, buf, &mut out);
            out
        };
        let mut shared = MnnBuffers::default();
        let big = run(&a, &b, &mut shared);
        let small = run(&small_a, &small_b, &mut shared);
        assert_eq!(small, run(&small_a, &small_b, &mut MnnBuffers::default()));
        assert_eq!(big, run(&a, &b, &mut MnnBuffers::default()));
        assert!(!small.pairs.is_empty() && !big.pairs.is_empty());
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
