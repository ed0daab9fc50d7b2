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
    /// The int8 screen's quantized sides and the pairs it lets through ([`screen`]).
    #[cfg(target_arch = "x86_64")]
    screen: screen::Buffers,
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
            row.len().is_multiple_of(LANES)
                && col_best.len() == row.len()
                && col_row.len() == row.len()
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
///
/// Where the CPU has AVX-512 VNNI, there is no ratio test and the floor is at least
/// [`screen::LOWEST_FLOOR`], an int8 product screens the pairs first ([`screen`]): only pairs whose
/// similarity can reach the floor are computed in f32, and the matches are those of the full
/// product (the same pairs; the similarities agree to float rounding, so only a tie within about
/// 1e-6 could go the other way).
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
    #[cfg(target_arch = "x86_64")]
    if screen::applies(dim, params) && screen::available() {
        let (a, b) = (&a[..n * dim], &b[..m * dim]);
        if screen::mutual_nearest(a, b, dim, params.min_similarity, &mut buf.screen, out) {
            return;
        }
    }
    mutual_nearest_full(a, b, dim, params, buf, out)
}

/// [`mutual_nearest`] from the whole f32 similarity matrix (`dim > 0`, both sides non-empty).
fn mutual_nearest_full(
    a: &[f32],
    b: &[f32],
    dim: usize,
    params: &MnnParams,
    buf: &mut MnnBuffers,
    out: &mut Matches,
) {
    let (n, m) = (a.len() / dim, b.len() / dim);
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

/// An int8 screen for [`mutual_nearest`] with a high similarity floor.
///
/// A mutual match needs a cosine of at least the floor (0.82 for XFeat), which few pairs reach. Each
/// descriptor is quantized to int8 with its own scale (`q = round(x * 127 / max|x|)`), and one
/// AVX-512 VNNI product (`vpdpbusd`: 64 multiply-adds of bytes an instruction, four times the f32
/// rate) gives every pair's approximate similarity with a bound on its error: with `e` the
/// rounding of a descriptor (`|e| <= sqrt(dim) / (2 scale)`), `|a.b - qa.qb / (sa sb)| <=
/// |a||eb| + |b||ea| + |ea||eb|`. A pair whose approximation plus its bound stays under the floor
/// cannot be a match, nor the best of its row or column among those at the floor; the others are
/// computed again in f32 and matched as the full product would match them: every similarity at
/// or above the floor is among them, so each row's and each column's best at the floor is found
/// (first maximum on ties), and a row whose best is under the floor matches nothing either way.
/// Not used with a ratio test (it needs each row's second best, however low).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
pub mod screen {
    use crate::Matches;
    use std::arch::x86_64::*;

    /// Lowest similarity floor the screen is used for: under it too many pairs pass the screen
    /// for it to pay.
    pub const LOWEST_FLOOR: f32 = 0.5;

    /// Columns of one AVX-512 register of i32 sums.
    const COLS: usize = 16;

    /// Rounding of the f32 arithmetic around the exact integer products, added to every bound.
    const SLACK: f32 = 1e-4;

    /// Buffers reused from call to call.
    #[derive(Debug, Default)]
    pub struct Buffers {
        /// The rows (and their `dim`) that `qa` and the per-row values below were made from.
        a_src: Vec<f32>,
        a_dim: usize,
        /// Rows of `a` as unsigned bytes (`q + 128`), row-major.
        qa: Vec<u8>,
        /// Per row of `a`: 1 / scale, the norm and the rounding bound.
        a_inv: Vec<f32>,
        a_norm: Vec<f32>,
        a_err: Vec<f32>,
        /// Rows of `b` as signed bytes packed for the kernel: for each group of 4 values, the
        /// columns in blocks of [`COLS`], 4 bytes each (`[group][column][4]`, columns padded).
        qb: Vec<i8>,
        /// Per column of `b`: the sum of its bytes (undoes `a`'s offset), 1 / scale, norm, bound.
        b_sum: Vec<i32>,
        b_inv: Vec<f32>,
        b_norm: Vec<f32>,
        b_err: Vec<f32>,
        /// One row's bytes.
        row: Vec<i8>,
        /// Pairs that pass the screen, with their f32 similarity.
        pairs: Vec<(u32, u32, f32)>,
        /// The passing pairs of each row of the tile of rows at hand (columns ascending), moved
        /// into `pairs` row by row when the tile is done, so `pairs` comes out in row order.
        tile_rows: [Vec<(u32, u32, f32)>; ROWS],
        /// Per column: the best similarity among passing pairs and its row.
        col_best: Vec<(f32, u32)>,
    }

    /// Whether the screen is sound and worth it for these settings.
    pub fn applies(dim: usize, params: &super::MnnParams) -> bool {
        params.ratio.is_none()
            && params.min_similarity >= LOWEST_FLOOR
            && dim > 0
            && dim.is_multiple_of(4)
            && dim <= 1024
    }

    /// Whether this CPU runs the screen (AVX-512 F, BW and VNNI).
    pub fn available() -> bool {
        std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512bw")
            && std::is_x86_feature_detected!("avx512vnni")
    }

    /// One row quantized into `q` (as long as `row`, a multiple of 4 values): 1 / scale, the
    /// row's norm and its rounding bound, or `None` when a value is not finite. Every loop is
    /// branch-free and vectorises.
    #[inline(always)]
    fn quantize_row(row: &[f32], q: &mut [i8]) -> Option<(f32, f32, f32)> {
        // Eight running maxima and sums.
        let (mut top, mut sums) = ([0f32; 8], [0f32; 8]);
        let chunks = row.chunks_exact(8);
        let tail = chunks.remainder();
        for c in chunks {
            for l in 0..8 {
                top[l] = top[l].max(c[l].abs());
                sums[l] += c[l] * c[l];
            }
        }
        for (l, &v) in tail.iter().enumerate() {
            top[l] = top[l].max(v.abs());
            sums[l] += v * v;
        }
        let amax = top.iter().fold(0f32, |a, &b| a.max(b));
        let sq: f32 = sums.iter().sum();
        // A NaN or an infinity anywhere makes the sum of squares non-finite.
        if !sq.is_finite() {
            return None;
        }
        if amax == 0.0 {
            q.fill(0);
            return Some((0.0, 0.0, 0.0));
        }
        let scale = 127.0 / amax;
        // Round to nearest (ties to even) by the 1.5 * 2^23 trick: exact for |x| < 2^22, and
        // |x| <= 127 here; no libm call.
        const ROUND: f32 = 12_582_912.0;
        for (o, &v) in q.iter_mut().zip(row) {
            *o = ((v * scale + ROUND) - ROUND).clamp(-127.0, 127.0) as i32 as i8;
        }
        let half_sqrt_dim = 0.5 * (row.len() as f32).sqrt();
        Some((amax / 127.0, sq.sqrt(), half_sqrt_dim / scale))
    }

    /// [`quantize_row`] sixteen values at a time with AVX-512 where the row allows it (a multiple
    /// of 16 values): the same scale and bound, values rounded to nearest by the conversion.
    /// Safety: call only where AVX-512 F and BW are present (from [`quantize_sides`]); every load
    /// and store is at `k..k + 16` with `k + 16 <= row.len() == q.len()` (checked first).
    #[inline(always)]
    unsafe fn quantize(row: &[f32], q: &mut [i8]) -> Option<(f32, f32, f32)> {
        if !row.len().is_multiple_of(16) || q.len() != row.len() {
            return quantize_row(row, q);
        }
        let abs_mask = _mm512_set1_epi32(0x7fff_ffff);
        let (mut top, mut sums) = (_mm512_setzero_ps(), _mm512_setzero_ps());
        for k in (0..row.len()).step_by(16) {
            let v = _mm512_loadu_ps(row.as_ptr().add(k));
            let a = _mm512_castsi512_ps(_mm512_and_si512(_mm512_castps_si512(v), abs_mask));
            top = _mm512_max_ps(top, a);
            sums = _mm512_add_ps(sums, _mm512_mul_ps(v, v));
        }
        let sq = _mm512_reduce_add_ps(sums);
        // A NaN or an infinity anywhere makes the sum of squares non-finite.
        if !sq.is_finite() {
            return None;
        }
        let amax = _mm512_reduce_max_ps(top);
        if amax == 0.0 {
            q.fill(0);
            return Some((0.0, 0.0, 0.0));
        }
        let scale = 127.0 / amax;
        let sv = _mm512_set1_ps(scale);
        for k in (0..row.len()).step_by(16) {
            let v = _mm512_mul_ps(_mm512_loadu_ps(row.as_ptr().add(k)), sv);
            // Rounded to nearest (the default rounding mode), then saturated to i8.
            let b = _mm512_cvtsepi32_epi8(_mm512_cvtps_epi32(v));
            _mm_storeu_si128(q.as_mut_ptr().add(k) as *mut __m128i, b);
        }
        let half_sqrt_dim = 0.5 * (row.len() as f32).sqrt();
        Some((amax / 127.0, sq.sqrt(), half_sqrt_dim / scale))
    }

    /// Whether two slices hold the same values bit for bit (one `memcmp`, where comparing as
    /// floats would go value by value).
    fn same_bits(x: &[f32], y: &[f32]) -> bool {
        // SAFETY: any initialised f32 is four initialised bytes; the views cover exactly the
        // slices and live no longer than the borrows.
        let bytes =
            |v: &[f32]| unsafe { std::slice::from_raw_parts(v.as_ptr() as *const u8, v.len() * 4) };
        x.len() == y.len() && bytes(x) == bytes(y)
    }

    /// Both sides quantized into `s` (the query side `a` only when it differs from the last
    /// call's); false when a value is not finite.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn quantize_sides(s: &mut Buffers, a: &[f32], b: &[f32], dim: usize) -> bool {
        let (n, m) = (a.len() / dim, b.len() / dim);
        let (blocks, groups) = (m.div_ceil(COLS), dim / 4);
        s.row.clear();
        s.row.resize(dim, 0);
        // A vote matches one query against image after image: its side is quantized once, and
        // again only when the rows differ from the last call's.
        if !(s.a_dim == dim && same_bits(&s.a_src, a)) {
            s.a_src.clear();
            s.a_dim = 0;
            s.qa.clear();
            s.qa.resize(n * dim, 128);
            for v in [&mut s.a_inv, &mut s.a_norm, &mut s.a_err] {
                v.clear();
            }
            for (x, qa) in a.chunks_exact(dim).zip(s.qa.chunks_exact_mut(dim)) {
                let Some((inv, norm, err)) = quantize(x, &mut s.row) else {
                    return false;
                };
                // Unsigned for `vpdpbusd`: q + 128, undone with the columns' sums.
                for (o, &v) in qa.iter_mut().zip(&s.row) {
                    *o = (v as u8) ^ 0x80;
                }
                s.a_inv.push(inv);
                s.a_norm.push(norm);
                s.a_err.push(err);
            }
            s.a_src.extend_from_slice(a);
            s.a_dim = dim;
        }
        for v in [&mut s.b_inv, &mut s.b_norm, &mut s.b_err] {
            v.clear();
        }
        s.qb.clear();
        s.qb.resize(groups * blocks * COLS * 4, 0);
        s.b_sum.clear();
        s.b_sum.resize(blocks * COLS, 0);
        let stride = blocks * COLS * 4;
        for (c, x) in b.chunks_exact(dim).enumerate() {
            let Some((inv, norm, err)) = quantize(x, &mut s.row) else {
                return false;
            };
            for (g, four) in s.row.chunks_exact(4).enumerate() {
                s.qb[g * stride + c * 4..g * stride + c * 4 + 4].copy_from_slice(four);
            }
            s.b_sum[c] = s.row.iter().map(|&v| v as i32).sum();
            s.b_inv.push(inv);
            s.b_norm.push(norm);
            s.b_err.push(err);
        }
        for v in [&mut s.b_inv, &mut s.b_norm, &mut s.b_err] {
            v.resize(blocks * COLS, 0.0);
        }
        true
    }

    /// The f32 similarity of every screened pair (`(row of a, row of b, _)`).
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn similarities(pairs: &mut [(u32, u32, f32)], a: &[f32], b: &[f32], dim: usize) {
        for p in pairs.iter_mut() {
            let (i, j) = (p.0 as usize, p.1 as usize);
            p.2 = dot(&a[i * dim..(i + 1) * dim], &b[j * dim..(j + 1) * dim]);
        }
    }

    /// Mutual nearest neighbours of the rows of `a` (n x dim) and `b` (m x dim) with similarity at
    /// least `floor`, appended to `out` as [`super::mutual_nearest`] would (rows ascending). False
    /// (and nothing appended) when a value is not finite: the caller then runs the full product.
    /// Call only where [`available`] and [`applies`].
    pub fn mutual_nearest(
        a: &[f32],
        b: &[f32],
        dim: usize,
        floor: f32,
        s: &mut Buffers,
        out: &mut Matches,
    ) -> bool {
        assert!(
            available() && dim.is_multiple_of(4) && dim > 0,
            "screen called where it does not apply"
        );
        let (n, m) = (a.len() / dim, b.len() / dim);
        // SAFETY: AVX-512 F/BW/VNNI are present (asserted above), all `quantize_sides` needs.
        if !unsafe { quantize_sides(s, a, b, dim) } {
            return false;
        }
        s.pairs.clear();
        // SAFETY: AVX-512 F/BW/VNNI are present (asserted above); `screen_pairs` reads `qa` rows
        // of `dim` bytes, `qb` groups of `blocks * COLS * 4` bytes and the per-column vectors of
        // `blocks * COLS` values (`blocks = m / COLS` rounded up), the lengths `quantize_sides` set.
        unsafe { screen_pairs(s, n, m, dim, floor) };
        debug_assert!(
            s.pairs
                .windows(2)
                .all(|w| (w[0].0, w[0].1) < (w[1].0, w[1].1)),
            "row order, columns ascending"
        );
        // The passing pairs in f32, then the full product's rule among them.
        // SAFETY: as above; `similarities` indexes `a` and `b` by the pairs' rows and columns,
        // which are below `n` and `m`.
        unsafe { similarities(&mut s.pairs, a, b, dim) };
        s.col_best.clear();
        s.col_best.resize(m, (f32::NEG_INFINITY, 0));
        for &(i, j, v) in &s.pairs {
            let c = &mut s.col_best[j as usize];
            if v > c.0 {
                *c = (v, i);
            }
        }
        // Pairs are in row order, columns ascending within a row.
        let mut k = 0;
        while k < s.pairs.len() {
            let i = s.pairs[k].0;
            let (mut bj, mut b1) = (0u32, f32::NEG_INFINITY);
            while k < s.pairs.len() && s.pairs[k].0 == i {
                let (_, j, v) = s.pairs[k];
                if v > b1 {
                    (bj, b1) = (j, v);
                }
                k += 1;
            }
            if b1 >= floor && s.col_best[bj as usize].1 == i {
                out.pairs.push((i, bj));
                out.scores.push(b1);
            }
        }
        true
    }

    /// The dot product of two rows, in eight running sums (vectorised).
    #[inline(always)]
    fn dot(x: &[f32], y: &[f32]) -> f32 {
        let mut acc = [0f32; 8];
        let (xc, yc) = (x.chunks_exact(8), y.chunks_exact(8));
        let (xr, yr) = (xc.remainder(), yc.remainder());
        for (p, q) in xc.zip(yc) {
            for l in 0..8 {
                acc[l] += p[l] * q[l];
            }
        }
        let tail: f32 = xr.iter().zip(yr).map(|(p, q)| p * q).sum();
        acc.iter().sum::<f32>() + tail
    }

    /// Rows and column blocks screened together: independent sums, so the multiply-adds overlap,
    /// and each loaded row group and column block serves several of them.
    const ROWS: usize = 4;
    const BLOCKS: usize = 4;

    /// Every pair whose approximate similarity plus its bound reaches `floor`, into `s.pairs`.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn screen_pairs(s: &mut Buffers, n: usize, m: usize, dim: usize, floor: f32) {
        let blocks = m.div_ceil(COLS);
        let mut i = 0;
        while i < n {
            let rows = ROWS.min(n - i);
            let mut blk = 0;
            while blk < blocks {
                let count = BLOCKS.min(blocks - blk);
                if rows == ROWS && count == BLOCKS {
                    tile::<ROWS, BLOCKS>(s, i, 0, blk, m, dim, floor);
                } else {
                    for r in 0..rows {
                        for k in 0..count {
                            tile::<1, 1>(s, i + r, r, blk + k, m, dim, floor);
                        }
                    }
                }
                blk += count;
            }
            // The tile's rows in order; within a row, blocks and lanes came out ascending.
            for r in 0..rows {
                let (pairs, row) = (&mut s.pairs, &mut s.tile_rows[r]);
                pairs.append(row);
            }
            i += rows;
        }
    }

    /// [`screen_pairs`] for rows `i0..i0 + R` (rows `r0..r0 + R` of the tile of rows at hand)
    /// and column blocks `b0..b0 + C`.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn tile<const R: usize, const C: usize>(
        s: &mut Buffers,
        i0: usize,
        r0: usize,
        b0: usize,
        m: usize,
        dim: usize,
        floor: f32,
    ) {
        let blocks = m.div_ceil(COLS);
        let stride = blocks * COLS * 4;
        let floor_v = _mm512_set1_ps(floor - SLACK);
        let offset = _mm512_set1_epi32(128);
        let mut acc = [[_mm512_setzero_si512(); C]; R];
        for g in 0..dim / 4 {
            let mut bv = [_mm512_setzero_si512(); C];
            for (k, b) in bv.iter_mut().enumerate() {
                *b = _mm512_loadu_si512(
                    s.qb.as_ptr().add(g * stride + (b0 + k) * COLS * 4) as *const _
                );
            }
            for (r, acc) in acc.iter_mut().enumerate() {
                let four =
                    (s.qa.as_ptr().add((i0 + r) * dim + g * 4) as *const i32).read_unaligned();
                let av = _mm512_set1_epi32(four);
                for (a, b) in acc.iter_mut().zip(&bv) {
                    *a = _mm512_dpbusd_epi32(*a, av, *b);
                }
            }
        }
        for k in 0..C {
            let c = (b0 + k) * COLS;
            let sum = _mm512_mullo_epi32(
                offset,
                _mm512_loadu_si512(s.b_sum.as_ptr().add(c) as *const _),
            );
            let b_inv = _mm512_loadu_ps(s.b_inv.as_ptr().add(c));
            let b_norm = _mm512_loadu_ps(s.b_norm.as_ptr().add(c));
            let b_err = _mm512_loadu_ps(s.b_err.as_ptr().add(c));
            let valid = if c + COLS > m {
                ((1u32 << (m - c)) - 1) as u16
            } else {
                u16::MAX
            };
            for (r, acc) in acc.iter().enumerate() {
                let i = i0 + r;
                let (a_inv, a_norm, a_err) = (
                    _mm512_set1_ps(s.a_inv[i]),
                    _mm512_set1_ps(s.a_norm[i]),
                    _mm512_set1_ps(s.a_err[i]),
                );
                let dot = _mm512_sub_epi32(acc[k], sum);
                let approx = _mm512_mul_ps(_mm512_mul_ps(_mm512_cvtepi32_ps(dot), a_inv), b_inv);
                // |a| eb + |b| ea + ea eb
                let bound = _mm512_add_ps(
                    _mm512_add_ps(_mm512_mul_ps(a_norm, b_err), _mm512_mul_ps(b_norm, a_err)),
                    _mm512_mul_ps(a_err, b_err),
                );
                let mut mask =
                    _mm512_cmp_ps_mask::<_CMP_GE_OQ>(_mm512_add_ps(approx, bound), floor_v) & valid;
                while mask != 0 {
                    let l = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    s.tile_rows[r0 + r].push((i as u32, (c + l) as u32, 0.0));
                }
            }
        }
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
    #[cfg(target_arch = "x86_64")]
    fn the_int8_screen_keeps_exactly_the_full_products_matches() {
        if !screen::available() {
            eprintln!("skipped: this CPU has no AVX-512 VNNI, so the screen never runs here");
            return;
        }
        // Near copies at several noise levels, so similarities crowd the floor from both sides.
        let a = features(512, 64, 11);
        let mut total = 0;
        for (trial, mix) in [0.2f32, 0.45, 0.6, 0.75].into_iter().enumerate() {
            let noise = features(480, 64, 20 + trial as u64);
            let mut b = noise.clone();
            for j in 0..480 {
                let i = (j * 13 + trial) % 512;
                let mixed: Vec<f32> = a
                    .descriptor(i)
                    .iter()
                    .zip(noise.descriptor(j))
                    .map(|(x, y)| x + mix * y)
                    .collect();
                let norm = mixed.iter().map(|v| v * v).sum::<f32>().sqrt();
                b.descriptors[j * 64..(j + 1) * 64]
                    .iter_mut()
                    .zip(&mixed)
                    .for_each(|(d, v)| *d = v / norm);
            }
            for floor in [0.5, 0.7, 0.82, 0.9] {
                let p = MnnParams {
                    min_similarity: floor,
                    ..MnnParams::default()
                };
                assert!(screen::applies(64, &p));
                let (mut screened, mut full) = (Matches::default(), Matches::default());
                let mut buf = MnnBuffers::default();
                mutual_nearest(
                    &a.descriptors,
                    &b.descriptors,
                    64,
                    &p,
                    &mut buf,
                    &mut screened,
                );
                mutual_nearest_full(&a.descriptors, &b.descriptors, 64, &p, &mut buf, &mut full);
                assert_eq!(screened.pairs, full.pairs, "noise {mix}, floor {floor}");
                for (x, y) in screened.scores.iter().zip(&full.scores) {
                    assert!((x - y).abs() < 1e-5, "{x} {y}");
                }
                total += full.pairs.len();
            }
        }
        assert!(total > 1000, "{total} matches over all cases");
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
