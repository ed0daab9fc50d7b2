//! Verification: does the estimated pose explain the query's own pixels, not just its keypoints?
//!
//! Registration only sees the matched keypoints, and on a map of similar rooms a few dozen of them can
//! agree on a wrong pose (the same sofa in another flat, a pose slid along a flat wall). RGB-D gives a
//! much denser witness: under the right pose the query's depth, moved into a database view, lands on
//! that view's surfaces, with matching colour, and never in the free space that view saw through.
//!
//! The checks run on small images ([`Thumb`], about 32 px of focal length: 64 x 64 for HPointLoc's
//! camera) kept in the map for every database image (u16 millimetres and 8-bit grey, 12 KiB an image),
//! so verifying five candidates against their nearby views costs about a tenth of a query's time
//! (BENCHMARKS.md) and stays within the memory budget. They produce an
//! [`Evidence`] vector per candidate pose; [`crate::calibration`] turns it into the probability that the
//! pose is within (1 m, 10 deg) of the truth.
//!
//! Sources: the depth test with a tolerance growing with range and the free-space ("see-through")
//! violation follow the model-based verification of RGB-D relocalisers and KinectFusion-style
//! projective association (Newcombe et al., 2011); colour agreement as a correlation is invariant to the
//! gain and offset of an auto-exposing camera, and measured within small tiles as well (local
//! normalised cross-correlation, as in direct image alignment) it is nearly invariant to lighting
//! that changes the shade of each surface differently (a lamp off, daylight from another side).

use nalgebra::{Isometry3, Vector3};
use pntr_core::{DepthMap, Intrinsics, RgbImage};
use serde::Serialize;

/// Focal length, in thumbnail pixels, that every thumbnail is reduced to (whatever the camera).
pub const THUMB_FOCAL_PX: f64 = 32.0;
/// Largest thumbnail side, pixels (bounds the dense checks' cost for any declared camera).
pub const MAX_THUMB_SIDE: u32 = 256;

/// A reduced RGB-D image for dense checks: block medians of depth and block means of grey.
#[derive(Debug, Clone, PartialEq)]
pub struct Thumb {
    /// Width in thumbnail pixels.
    pub width: u32,
    /// Height in thumbnail pixels.
    pub height: u32,
    /// Intrinsics of the thumbnail (OpenCV convention, in thumbnail pixels).
    pub intrinsics: Intrinsics,
    /// Depth in millimetres, row-major; 0 = invalid.
    pub depth_mm: Vec<u16>,
    /// Luminance 0..255, row-major.
    pub gray: Vec<u8>,
}

impl Thumb {
    /// Reduce an RGB-D frame with camera `k` by the integer block size that brings its focal length
    /// nearest to [`THUMB_FOCAL_PX`] (4 for HPointLoc's f = 128). Depth: the median of the block's
    /// valid pixels (invalid when fewer than half are valid), so edges keep one surface instead of a
    /// blend; grey: the block mean.
    /// The block size is clamped so that the thumbnail is at most [`MAX_THUMB_SIDE`] a side and the
    /// block no larger than the image, whatever focal length a caller declares.
    pub fn new(rgb: &RgbImage, depth: &DepthMap, k: &Intrinsics) -> Self {
        let side = rgb.width.max(rgb.height).max(1);
        let by_focal = (k.fx.min(k.fy) / THUMB_FOCAL_PX).round();
        let by_focal = if by_focal.is_finite() {
            by_focal.clamp(1.0, side as f64) as u32
        } else {
            1
        };
        Self::reduced(rgb, depth, k, by_focal.max(side.div_ceil(MAX_THUMB_SIDE)))
    }

    /// The reduction of [`Thumb::new`] by blocks of `s` x `s` pixels (`s` >= 1): the block's median
    /// valid depth and mean grey, the intrinsics scaled to the thumbnail's pixels.
    pub fn reduced(rgb: &RgbImage, depth: &DepthMap, k: &Intrinsics, s: u32) -> Self {
        let s = s.max(1);
        let (w, h) = ((rgb.width / s).max(1), (rgb.height / s).max(1));
        let half = (s as f64 - 1.0) / 2.0;
        let intrinsics = Intrinsics {
            fx: k.fx / s as f64,
            fy: k.fy / s as f64,
            cx: (k.cx - half) / s as f64,
            cy: (k.cy - half) / s as f64,
            width: w,
            height: h,
            distortion: [0.0; 5],
        };
        let mut thumb = Self {
            width: w,
            height: h,
            intrinsics,
            depth_mm: vec![0u16; (w * h) as usize],
            gray: vec![0u8; (w * h) as usize],
        };
        reduce_blocks_best(rgb, depth, s, &mut thumb);
        thumb
    }

    /// Depth in metres at (col, row), `None` where invalid or outside.
    pub fn depth_m(&self, col: u32, row: u32) -> Option<f64> {
        if col >= self.width || row >= self.height {
            return None;
        }
        let d = self.depth_mm[(row * self.width + col) as usize];
        (d > 0).then(|| metres_of_mm()[d as usize])
    }

    /// Bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.depth_mm.len() * 2 + self.gray.len()
    }

    /// Number of valid depth samples.
    pub fn valid(&self) -> usize {
        self.depth_mm.iter().filter(|&&d| d > 0).count()
    }
}

/// [`Thumb::new`]'s reduction of `rgb` and `depth` by blocks of `s` x `s` pixels into `out`'s
/// `depth_mm` and `gray` (`out.width` x `out.height`, zeroed).
#[inline(always)]
fn reduce_blocks(rgb: &RgbImage, depth: &DepthMap, s: u32, out: &mut Thumb) {
    let (w, h) = (out.width, out.height);
    let (depth_mm, gray) = (&mut out.depth_mm, &mut out.gray);
    let (wu, su, ss) = (w as usize, s as usize, (s * s) as usize);
    // One row of blocks at a time, image row by image row: each block's grey sum takes its
    // pixels in the same order as a block-by-block loop (rows, then columns), so the sums are
    // the same to the bit, but the blocks of a row are independent chains of additions. The
    // row's luminance and depth bits are made first, in loops without branches.
    let mut sums = vec![0f32; wu];
    // Per block, its pixels' depth bit patterns, u32::MAX where invalid (above every valid one).
    let mut bits = vec![u32::MAX; wu * ss];
    let used = (wu * su).min(rgb.width as usize);
    let mut lum = vec![0f32; used];
    let mut row_bits = vec![u32::MAX; used];
    let stride = rgb.width as usize;
    // Block `c`'s columns of the image (all `s` of them unless the image is narrower than a block).
    let columns = |c: usize| (c * su).min(used)..((c + 1) * su).min(used);
    for r in 0..h {
        sums.fill(0.0);
        bits.fill(u32::MAX);
        let rows = r * s..((r + 1) * s).min(rgb.height);
        let block_rows = rows.len();
        for (k, y) in rows.enumerate() {
            let row = y as usize * stride;
            let px = &rgb.data[row * 3..(row + used) * 3];
            for (l, p) in lum.iter_mut().zip(px.chunks_exact(3)) {
                *l = pntr_core::image::luminance(p);
            }
            for (x, b) in row_bits.iter_mut().enumerate() {
                let d = depth.data.get(row + x).copied().unwrap_or(0.0);
                // Positive finite floats order as their bit patterns do.
                *b = if d.is_finite() && d > 0.0 {
                    d.to_bits()
                } else {
                    u32::MAX
                };
            }
            for (c, sum) in sums.iter_mut().enumerate() {
                let x = columns(c);
                for &l in &lum[x.clone()] {
                    *sum += l;
                }
                let o = c * ss + k * su;
                bits[o..o + x.len()].copy_from_slice(&row_bits[x]);
            }
        }
        for c in 0..wu {
            let o = r as usize * wu + c;
            // The block's pixels.
            let n = (block_rows * columns(c).len()) as u32;
            gray[o] = (sums[c] / n.max(1) as f32).round().clamp(0.0, 255.0) as u8;
            let block = &mut bits[c * ss..(c + 1) * ss];
            let valid = block.iter().filter(|&&b| b != u32::MAX).count();
            if valid * 2 >= n as usize && valid > 0 {
                // The invalid pixels rank after every valid one, so the valid values' median
                // (rank valid / 2) is the whole block's element of that rank.
                let med = f32::from_bits(rank_bits(block, valid / 2));
                depth_mm[o] = (med * 1000.0).round().clamp(1.0, 65535.0) as u16;
            }
        }
    }
}

/// [`reduce_blocks`] compiled for AVX2 (the block medians' ranking in eight lanes), chosen at run
/// time where the CPU has it. The same results: integer comparisons, and float arithmetic
/// without fused multiply-adds (AVX2 does not enable them).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn reduce_blocks_avx2(rgb: &RgbImage, depth: &DepthMap, s: u32, out: &mut Thumb) {
    reduce_blocks(rgb, depth, s, out)
}

/// [`reduce_blocks`], on AVX2 where this CPU has it.
fn reduce_blocks_best(rgb: &RgbImage, depth: &DepthMap, s: u32, out: &mut Thumb) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        #[allow(unsafe_code)]
        // SAFETY: the CPU has AVX2 (checked on the line above), the only requirement of the
        // target feature; the function itself is safe code.
        unsafe {
            reduce_blocks_avx2(rgb, depth, s, out)
        };
        return;
    }
    reduce_blocks(rgb, depth, s, out)
}

/// The element of rank `m` of `v` in ascending order, as `select_nth_unstable(m)` gives it. Blocks
/// of 16 values (4 x 4 pixels, a thumbnail of HPointLoc's camera) are ranked without branches: a
/// value is the one when at most `m` values are below it and more than `m` are at most it.
#[inline(always)]
fn rank_bits(v: &mut [u32], m: usize) -> u32 {
    let Ok(block) = <&[u32; 16]>::try_from(&*v) else {
        return *v.select_nth_unstable(m).1;
    };
    // Counts for all sixteen values at once (lane `i` counts for `block[i]`), one value of the
    // block against all of them per step: vector additions, no horizontal sums.
    let (mut below, mut at_most) = ([0u32; 16], [0u32; 16]);
    for &y in block {
        for i in 0..16 {
            below[i] += (y < block[i]) as u32;
            at_most[i] += (y <= block[i]) as u32;
        }
    }
    let m = m as u32;
    let mut out = block[0];
    for i in 0..16 {
        if below[i] <= m && m < at_most[i] {
            out = block[i];
        }
    }
    out
}

/// Metres of every thumbnail depth value: entry `d` is `d as f64 / 1000.0`, the same to the bit,
/// made once per process (512 KiB). The dense checks look a depth up for every sample they move
/// and every sample they land on; a table lookup costs a fraction of a division there (a profile
/// of the checks had most of their time waiting on the two divisions of each sample).
fn metres_of_mm() -> &'static [f64] {
    static TABLE: std::sync::OnceLock<Vec<f64>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| (0..=u16::MAX).map(|d| d as f64 / 1000.0).collect())
}

/// Depth tolerance (metres) of the dense test at range `z_m`: 4 cm plus 3% of the range (thumbnail
/// pixels span z/32 m, and sensor noise grows with range).
pub fn depth_tolerance_m(z_m: f64) -> f64 {
    0.04 + 0.03 * z_m
}

/// What moving one thumbnail's samples into another view showed.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DenseCounts {
    /// Valid samples of the moved thumbnail.
    pub valid: usize,
    /// Samples that land inside the other view on a valid depth.
    pub inside: usize,
    /// ... whose depth agrees with the other view's within [`depth_tolerance_m`].
    pub agree: usize,
    /// ... that lie in front of the other view's surface: the other camera saw through them.
    pub violate: usize,
    /// Sum of products and squares of the grey values of agreeing samples (for the correlation).
    gray: [f64; 5],
    /// Sum over the textured tiles of the moved thumbnail of samples x the tile's grey correlation,
    /// and the samples of those tiles (for [`DenseCounts::local_gray_correlation`]).
    local: [f64; 2],
}

impl DenseCounts {
    /// Add another count.
    pub fn add(&mut self, o: &DenseCounts) {
        self.valid += o.valid;
        self.inside += o.inside;
        self.agree += o.agree;
        self.violate += o.violate;
        for (a, b) in self.gray.iter_mut().zip(o.gray) {
            *a += b;
        }
        for (a, b) in self.local.iter_mut().zip(o.local) {
            *a += b;
        }
    }

    /// Share of inside samples whose depth agrees (0 when none is inside).
    pub fn agree_share(&self) -> f64 {
        self.agree as f64 / self.inside.max(1) as f64
    }

    /// Share of inside samples that violate the other view's free space.
    pub fn violate_share(&self) -> f64 {
        self.violate as f64 / self.inside.max(1) as f64
    }

    /// Share of valid samples that land inside the other view.
    pub fn overlap(&self) -> f64 {
        self.inside as f64 / self.valid.max(1) as f64
    }

    /// Pearson correlation of the grey values of agreeing samples (gain- and offset-invariant); 0
    /// with fewer than 16 samples or no variation.
    pub fn gray_correlation(&self) -> f64 {
        if self.agree < 16 {
            return 0.0;
        }
        pearson(&self.gray, self.agree as f64).unwrap_or(0.0)
    }

    /// Grey correlation within tiles of [`LOCAL_TILE`] x [`LOCAL_TILE`] thumbnail pixels of the moved
    /// thumbnail, averaged over the textured tiles weighted by their agreeing samples, -1..1 (0 when
    /// no tile has texture). Each tile has its own gain and offset, so a change of lighting that
    /// shades each surface differently (a lamp off, the sun elsewhere) leaves it nearly unchanged,
    /// unlike [`DenseCounts::gray_correlation`]; it is the local normalised cross-correlation of
    /// image alignment.
    pub fn local_gray_correlation(&self) -> f64 {
        if self.local[1] <= 0.0 {
            return 0.0;
        }
        (self.local[0] / self.local[1]).clamp(-1.0, 1.0)
    }
}

#[cfg(test)]
impl DenseCounts {
    /// Counts of `inside` samples, `agree` and `violate` of them, and a local grey correlation of
    /// `local_gray` (for tests of rules over counts).
    pub(crate) fn of(inside: usize, agree: usize, violate: usize, local_gray: f64) -> Self {
        DenseCounts {
            valid: inside,
            inside,
            agree,
            violate,
            gray: [0.0; 5],
            local: [local_gray * inside as f64, inside as f64],
        }
    }
}

/// Side, in thumbnail pixels, of the tiles of [`DenseCounts::local_gray_correlation`]: 4 (about 7
/// degrees of view, mostly one surface). Chosen by measurement: tiles of 4, 8 and 16 gave recall
/// 0.880, 0.860 and 0.834 with robot captures on the demo scene at the refitted calibrations'
/// thresholds (BENCHMARKS.md, "Grey correlation within tiles").
pub const LOCAL_TILE: u32 = 4;

/// Fewest agreeing samples a tile needs to count in the local correlation (of 16).
const LOCAL_MIN_SAMPLES: f64 = 12.0;

/// Pearson correlation from the sums `[a, b, aa, bb, ab]` of `n` pairs; `None` when either side has a
/// variance of at most one grey level squared (a flat surface: no texture to correlate).
fn pearson(sums: &[f64; 5], n: f64) -> Option<f64> {
    let [sa, sb, saa, sbb, sab] = *sums;
    let cov = sab / n - sa * sb / (n * n);
    let va = saa / n - sa * sa / (n * n);
    let vb = sbb / n - sb * sb / (n * n);
    (va > 1.0 && vb > 1.0).then(|| (cov / (va * vb).sqrt()).clamp(-1.0, 1.0))
}

/// Move every valid sample of `from` into `to` with `to_from_from` and compare depth and grey.
pub fn dense_check(from: &Thumb, to: &Thumb, to_from_from: &Isometry3<f64>) -> DenseCounts {
    dense_check_every(from, to, to_from_from, 1)
}

/// Buffers of [`dense_check_every`], reused from call to call on each thread (a query runs tens
/// of dense checks).
#[derive(Default)]
struct DenseScratch {
    /// Per sampled column: the back-projection factor `(u - cx) / fx`.
    xs: Vec<f64>,
    /// Per sampled column of the row at hand: the depth (metres, 0 where invalid), the moved
    /// point's depth and its pixel coordinates in the other view plus one half.
    z: Vec<f64>,
    moved: MovedRow,
    /// Per tile of [`LOCAL_TILE`] samples: the grey sums `[a, b, aa, bb, ab]` and the count, as
    /// integers (exact, so the same as the f64 sums they replace, in any order).
    tiles: Vec<[u32; 6]>,
}

/// One row of samples after [`move_row`]: per sampled column, the moved point's depth and its
/// pixel coordinates in the other view plus one half.
#[derive(Default)]
struct MovedRow {
    qz: Vec<f64>,
    pu: Vec<f64>,
    pv: Vec<f64>,
}

thread_local! {
    static DENSE_SCRATCH: std::cell::RefCell<DenseScratch> = Default::default();
}

/// A rigid motion and the other camera's projection, as plain numbers for [`move_row`].
struct Projection {
    r: [[f64; 3]; 3],
    t: [f64; 3],
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

/// One row of samples moved into the other camera: for each sampled column (back-projection factor
/// `xs[i]`, depth `z[i]` metres) at row factor `y`, the moved point's depth `qz[i]` and its pixel
/// coordinates plus one half (`pu[i]`, `pv[i]`, as [`Intrinsics::pixel_of`] adds before it
/// truncates). The operations and their order are those of `rotation * p + t`,
/// [`Intrinsics::project`] and [`Intrinsics::pixel_of`] on one sample, so every result is the
/// same to the bit; the loop has no branch and no dependence between columns, so it vectorises.
/// Where the depth is invalid or the point lies behind the camera the values are meaningless and
/// the caller skips them.
#[inline(always)]
fn move_row(m: &Projection, xs: &[f64], z: &[f64], y: f64, out: &mut MovedRow) {
    let MovedRow { qz, pu, pv } = out;
    let n = xs
        .len()
        .min(z.len())
        .min(qz.len())
        .min(pu.len())
        .min(pv.len());
    let r = &m.r;
    for i in 0..n {
        let z = z[i];
        let (px, py, pz) = (xs[i] * z, y * z, z);
        let x = r[0][0] * px + r[0][1] * py + r[0][2] * pz + m.t[0];
        let yq = r[1][0] * px + r[1][1] * py + r[1][2] * pz + m.t[1];
        let zq = r[2][0] * px + r[2][1] * py + r[2][2] * pz + m.t[2];
        qz[i] = zq;
        pu[i] = m.fx * x / zq + m.cx + 0.5;
        pv[i] = m.fy * yq / zq + m.cy + 0.5;
    }
}

/// [`move_row`] compiled for AVX (four lanes of f64), chosen at run time where the CPU has it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn move_row_avx(m: &Projection, xs: &[f64], z: &[f64], y: f64, out: &mut MovedRow) {
    move_row(m, xs, z, y, out)
}

/// [`move_row`], on AVX where this CPU has it (the same results: IEEE arithmetic lane by lane, no
/// fused multiply-add).
fn move_row_best(m: &Projection, xs: &[f64], z: &[f64], y: f64, out: &mut MovedRow) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx") {
        #[allow(unsafe_code)]
        // SAFETY: the CPU has AVX (checked on the line above), the only requirement of the
        // target feature; the function itself is safe code.
        unsafe {
            move_row_avx(m, xs, z, y, out)
        };
        return;
    }
    move_row(m, xs, z, y, out)
}

/// [`dense_check`] on every `step`-th row and column of `from` (a `step`² share of the samples).
///
/// The samples of a row are moved and projected first, all columns at once ([`move_row`]), then
/// looked up in `to` one by one; the counts and sums are those of the one-sample-at-a-time form to
/// the bit (a test holds it to that form).
pub fn dense_check_every(
    from: &Thumb,
    to: &Thumb,
    to_from_from: &Isometry3<f64>,
    step: u32,
) -> DenseCounts {
    DENSE_SCRATCH.with(|s| dense_check_with(from, to, to_from_from, step, &mut s.borrow_mut()))
}

fn dense_check_with(
    from: &Thumb,
    to: &Thumb,
    to_from_from: &Isometry3<f64>,
    step: u32,
    s: &mut DenseScratch,
) -> DenseCounts {
    let step = step.max(1) as usize;
    let mut c = DenseCounts::default();
    let kf = &from.intrinsics;
    let kt = &to.intrinsics;
    let rot = to_from_from.rotation.to_rotation_matrix();
    let rm = rot.matrix();
    let t = to_from_from.translation.vector;
    let m = Projection {
        r: [
            [rm[(0, 0)], rm[(0, 1)], rm[(0, 2)]],
            [rm[(1, 0)], rm[(1, 1)], rm[(1, 2)]],
            [rm[(2, 0)], rm[(2, 1)], rm[(2, 2)]],
        ],
        t: [t.x, t.y, t.z],
        fx: kt.fx,
        fy: kt.fy,
        cx: kt.cx,
        cy: kt.cy,
    };
    let (tw, th) = (to.width as f64, to.height as f64);
    // The sampled columns (`i * step`) and their back-projection factors, once per call.
    let n = (from.width as usize).div_ceil(step);
    let col_of = |i: usize| (i * step) as u32;
    s.xs.clear();
    s.xs.extend((0..n).map(|i| (col_of(i) as f64 - kf.cx) / kf.fx));
    for b in [&mut s.z, &mut s.moved.qz, &mut s.moved.pu, &mut s.moved.pv] {
        b.clear();
        b.resize(n, 0.0);
    }
    let tiles_across = from.width.div_ceil(LOCAL_TILE);
    // A tile holds at most ceil(LOCAL_TILE / step)² samples: from every other row and column on,
    // 4 or fewer, below LOCAL_MIN_SAMPLES, so no tile could count and the local correlation is 0
    // whatever the samples say. The tiles are kept only where one could count.
    let per_tile = (LOCAL_TILE as usize).div_ceil(step).pow(2) as f64;
    let with_tiles = per_tile >= LOCAL_MIN_SAMPLES;
    s.tiles.clear();
    if with_tiles {
        s.tiles.resize(
            (tiles_across * from.height.div_ceil(LOCAL_TILE)) as usize,
            [0; 6],
        );
    }
    // The grey sums of agreeing samples as integers: grey values are whole numbers, so these sums
    // are exact, and the f64 they become equals the f64 sums taken sample by sample (every partial
    // sum is a whole number below 2^53). u64: 65,536 samples of 255 x 255 would overflow u32.
    let mut gray = [0u64; 5];
    let fw = from.width as usize;
    let metres = metres_of_mm();
    for r in (0..from.height).step_by(step) {
        let y = (r as f64 - kf.cy) / kf.fy;
        let row = &from.depth_mm[r as usize * fw..(r as usize + 1) * fw];
        for (i, z) in s.z.iter_mut().enumerate() {
            // 0 (invalid) is 0 m, as before.
            *z = metres[row[col_of(i) as usize] as usize];
        }
        move_row_best(&m, &s.xs, &s.z, y, &mut s.moved);
        let tile_row = ((r / LOCAL_TILE) * tiles_across) as usize;
        for i in 0..n {
            let col = col_of(i);
            if row[col as usize] == 0 {
                continue;
            }
            c.valid += 1;
            let qz = s.moved.qz[i];
            // `Intrinsics::project`: behind the camera; `pixel_of`: outside the view.
            if qz <= 1e-9 {
                continue;
            }
            let (pu, pv) = (s.moved.pu[i], s.moved.pv[i]);
            if !(pu >= 0.0 && pv >= 0.0 && pu < tw && pv < th) {
                continue;
            }
            // Inside: `u < to.width` and `v < to.height` (the test above), as `depth_m` checks.
            let (u, v) = (pu as u32, pv as u32);
            let dt = to.depth_mm[(v * to.width + u) as usize];
            if dt == 0 {
                continue;
            }
            let zt = metres[dt as usize];
            c.inside += 1;
            let tol = depth_tolerance_m(qz);
            // Without branches from here: whether the depth agrees is a coin toss for a wrong
            // pose, and a mispredicted branch cost more than the whole sample's arithmetic. The
            // grey values of a sample that does not agree are multiplied by 0, so every sum is
            // the one of the agreeing samples alone.
            let agrees = (zt - qz).abs() <= tol;
            let violates = !agrees && zt > qz + tol;
            c.agree += agrees as usize;
            c.violate += violates as usize;
            let f = agrees as u32;
            let a = from
                .gray
                .get(r as usize * fw + col as usize)
                .copied()
                .unwrap_or(0) as u32
                * f;
            let b = to
                .gray
                .get((v * to.width + u) as usize)
                .copied()
                .unwrap_or(0) as u32
                * f;
            let (aa, bb, ab) = (a * a, b * b, a * b);
            gray[0] += a as u64;
            gray[1] += b as u64;
            gray[2] += aa as u64;
            gray[3] += bb as u64;
            gray[4] += ab as u64;
            if with_tiles {
                // At most LOCAL_TILE² = 16 samples a tile: sums far below u32::MAX.
                let t = &mut s.tiles[tile_row + (col / LOCAL_TILE) as usize];
                t[0] += a;
                t[1] += b;
                t[2] += aa;
                t[3] += bb;
                t[4] += ab;
                t[5] += f;
            }
        }
    }
    c.gray = gray.map(|v| v as f64);
    for t in &s.tiles {
        let n = t[5] as f64;
        if n < LOCAL_MIN_SAMPLES {
            continue;
        }
        let t = t.map(|v| v as f64);
        if let Some(r) = pearson(&[t[0], t[1], t[2], t[3], t[4]], n) {
            c.local[0] += n * r;
            c.local[1] += n;
        }
    }
    c
}

/// Shifts of the query camera that [`aliases`] tries along each of its image axes, both ways, metres:
/// 0.12 to 0.80 in steps of 4 cm (a tile period of a few centimetres more or less is still found: the
/// correlation of a periodic texture stays high over about a tenth of its period).
pub const ALIAS_SHIFTS_M: (f64, f64, f64) = (0.12, 0.80, 0.04);

/// The largest shift of the query camera along its own x axis (`[0]`) and y axis (`[1]`), metres,
/// under which the query's thumbnail fits the matched view as well as under `db_from_query` (0 when
/// none does): as many samples land inside (at least half as many), depth agrees on nearly as many
/// (within 5 points of the share) and the grey values correlate nearly as well (within 0.05, and at
/// least 0.5). Shifts of [`ALIAS_SHIFTS_M`] both ways are tried, on every third thumbnail row and column.
///
/// A plane with a periodic texture filling the view (tiles, a grid, panelling, shelving) looks the
/// same after a shift of one period: the keypoints may have been registered to any of the copies,
/// and nothing in the frame says which. The registration's inlier residuals cannot show this, so the
/// pipeline widens the answer's covariance along those axes by the shifts found.
pub fn aliases(query: &Thumb, matched: &Thumb, db_from_query: &Isometry3<f64>) -> [f64; 2] {
    const STEP: u32 = 3;
    let base = dense_check_every(query, matched, db_from_query, STEP);
    let (inside0, agree0, gray0) = (base.inside, base.agree_share(), base.gray_correlation());
    let mut out = [0.0; 2];
    if inside0 < 16 || gray0 < 0.5 {
        return out;
    }
    let (lo, hi, by) = ALIAS_SHIFTS_M;
    let n = ((hi - lo) / by).round() as usize;
    for (axis, best) in out.iter_mut().enumerate() {
        for k in (0..=n).rev() {
            let d = lo + by * k as f64;
            let fits = [d, -d].iter().any(|&s| {
                let mut v = Vector3::zeros();
                v[axis] = s;
                // The camera moved by v in its own frame: db_from_query * (query_from_moved = +v).
                let moved = db_from_query * nalgebra::Translation3::from(v);
                let c = dense_check_every(query, matched, &moved, STEP);
                c.inside * 2 >= inside0
                    && c.agree_share() >= agree0 - 0.05
                    && c.gray_correlation() >= (gray0 - 0.05).max(0.5)
            });
            if fits {
                *best = d;
                break;
            }
        }
    }
    out
}

/// Both directions: query samples into the database view and database samples into the query.
///
/// The grey sums of the two directions are pooled as they are, so the second direction's pairs come
/// with the roles of query and map exchanged, and the pooled correlation drops when the two images
/// differ in brightness (an exposure change), unlike one direction's. This is the `gray_correlation`
/// the shipped calibration was fitted on; keeping the query as the first image in both directions was
/// measured (BENCHMARKS.md, "Robot captures") and traded recall for wrong answers without a net gain.
pub fn dense_check_both(q: &Thumb, db: &Thumb, db_from_query: &Isometry3<f64>) -> DenseCounts {
    let mut c = dense_check(q, db, db_from_query);
    c.add(&dense_check(db, q, &db_from_query.inverse()));
    c
}

/// Share of the cells of a `grid` x `grid` partition of the image that hold at least one of `pixels`.
pub fn grid_coverage(pixels: &[[f32; 2]], width: u32, height: u32, grid: u32) -> f64 {
    let mut cells = vec![false; (grid * grid) as usize];
    for p in pixels {
        let cx = ((p[0].max(0.0) / width.max(1) as f32) * grid as f32) as u32;
        let cy = ((p[1].max(0.0) / height.max(1) as f32) * grid as f32) as u32;
        cells[(cy.min(grid - 1) * grid + cx.min(grid - 1)) as usize] = true;
    }
    cells.iter().filter(|&&b| b).count() as f64 / cells.len() as f64
}

/// Whether two poses agree within `metres` and `degrees`.
pub fn poses_agree(a: &Isometry3<f64>, b: &Isometry3<f64>, metres: f64, degrees: f64) -> bool {
    (a.translation.vector - b.translation.vector).norm() <= metres
        && a.rotation.angle_to(&b.rotation).to_degrees() <= degrees
}

/// Everything verification measured about one candidate pose: the calibration's input. Names are
/// the calibration file's `features`, in this order.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Evidence {
    /// Dense depth agreement with the matched view (both directions), 0..1.
    pub depth_agree: f64,
    /// Share of samples the matched view saw through (free-space violations), 0..1.
    pub free_space_violation: f64,
    /// Share of the query's samples that land inside the matched view, 0..1.
    pub overlap: f64,
    /// Depth agreement over every nearby map view (the matched image's Point and the candidates).
    pub views_agree: f64,
    /// Free-space violations over those views.
    pub views_violation: f64,
    /// Correlation of grey values on agreeing samples of the matched view, -1..1.
    pub gray_correlation: f64,
    /// Correlation of grey values on agreeing samples of the nearby views, -1..1: a pose turned by a
    /// room's symmetry keeps the depth but not the colour of the walls around.
    pub views_gray: f64,
    /// ln(1 + registration inliers).
    pub log_inliers: f64,
    /// Inliers over matched pairs with depth.
    pub inlier_ratio: f64,
    /// Share of a 4 x 4 grid of the query image holding an inlier keypoint.
    pub inlier_coverage: f64,
    /// Share of the other registered candidates whose pose agrees with this one (0.5 m, 10 deg).
    pub consensus: f64,
    /// Inliers of the strongest registered candidate whose pose disagrees, over this one's (0..2).
    pub rival_inliers: f64,
    /// `views_agree` of the best verified candidate whose pose disagrees (0 when none): high when the
    /// place is ambiguous (a symmetric room, repeated furniture).
    pub rival_agree: f64,
    /// Grey correlation within tiles with the matched view (both directions),
    /// [`DenseCounts::local_gray_correlation`], -1..1.
    pub local_gray: f64,
    /// The same over the nearby views, -1..1.
    pub views_local_gray: f64,
}

/// Names of [`Evidence`]'s fields, in order.
pub const EVIDENCE_NAMES: [&str; 15] = [
    "depth_agree",
    "free_space_violation",
    "overlap",
    "views_agree",
    "views_violation",
    "gray_correlation",
    "views_gray",
    "log_inliers",
    "inlier_ratio",
    "inlier_coverage",
    "consensus",
    "rival_inliers",
    "rival_agree",
    "local_gray",
    "views_local_gray",
];

impl Evidence {
    /// The values in [`EVIDENCE_NAMES`] order.
    pub fn values(&self) -> [f64; 15] {
        [
            self.depth_agree,
            self.free_space_violation,
            self.overlap,
            self.views_agree,
            self.views_violation,
            self.gray_correlation,
            self.views_gray,
            self.log_inliers,
            self.inlier_ratio,
            self.inlier_coverage,
            self.consensus,
            self.rival_inliers,
            self.rival_agree,
            self.local_gray,
            self.views_local_gray,
        ]
    }

    /// Grey agreement within tiles at best over the matched view ([`Evidence::local_gray`]) and the
    /// nearby ones ([`Evidence::views_local_gray`]), -1..1.
    pub fn best_local_gray(&self) -> f64 {
        self.local_gray.max(self.views_local_gray)
    }

    /// The registration's inlier count, from [`Evidence::log_inliers`].
    pub fn inliers(&self) -> usize {
        (self.log_inliers.exp() - 1.0).round().max(0.0) as usize
    }

    /// A one-line account of the checks, for NOT_LOCALIZED reasons.
    pub fn summary(&self) -> String {
        format!(
            "depth agrees on {:.0}% of pixels ({:.0}% over nearby views), {:.0}% seen through by the map, grey correlation {:.2} ({:.2} within tiles), {} inliers, {:.0}% of other candidates agree, a rival pose agrees on {:.0}%",
            100.0 * self.depth_agree,
            100.0 * self.views_agree,
            100.0 * self.free_space_violation,
            self.gray_correlation,
            self.local_gray,
            self.inliers(),
            100.0 * self.consensus,
            100.0 * self.rival_agree
        )
    }
}

/// Build the dense part of the evidence: the matched view and the nearby views.
pub fn dense_evidence(
    query: &Thumb,
    matched: &Thumb,
    db_from_query: &Isometry3<f64>,
    nearby: &[(&Thumb, Isometry3<f64>)],
) -> Evidence {
    // Both directions with the matched view, as `dense_check_both`; the first alone gives the overlap.
    let forward = dense_check(query, matched, db_from_query);
    let mut m = forward;
    m.add(&dense_check(matched, query, &db_from_query.inverse()));
    let mut all = m;
    let mut others = DenseCounts::default();
    for (t, view_from_query) in nearby {
        let c = dense_check(query, t, view_from_query);
        all.add(&c);
        others.add(&c);
    }
    Evidence {
        depth_agree: m.agree_share(),
        free_space_violation: m.violate_share(),
        overlap: forward.overlap(),
        views_agree: all.agree_share(),
        views_violation: all.violate_share(),
        gray_correlation: m.gray_correlation(),
        views_gray: others.gray_correlation(),
        local_gray: m.local_gray_correlation(),
        views_local_gray: others.local_gray_correlation(),
        ..Default::default()
    }
}

/// Convenience: a 3-vector from f32 triple.
pub fn vec3(p: [f32; 3]) -> Vector3<f64> {
    Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    fn wall_scene(shift: f64) -> (RgbImage, DepthMap, Intrinsics) {
        // A textured plane at 2 m with a box in front of its left half.
        let k = Intrinsics::hpointloc();
        let (w, h) = (256u32, 256u32);
        let mut rgb = vec![0u8; (w * h * 3) as usize];
        let mut depth = vec![0f32; (w * h) as usize];
        for r in 0..h {
            for c in 0..w {
                let i = (r * w + c) as usize;
                let x = (c as f64 - k.cx) / k.fx * 2.0 + shift;
                let g = if ((x * 3.0).floor() as i64).rem_euclid(2) == 0 {
                    40
                } else {
                    200
                };
                rgb[i * 3..i * 3 + 3].copy_from_slice(&[g, g, g]);
                depth[i] = if c < 100 { 1.2 } else { 2.0 };
            }
        }
        (
            RgbImage::new(w, h, rgb).unwrap(),
            DepthMap::from_metres(w, h, depth).unwrap(),
            k,
        )
    }

    /// The dense check one sample at a time with nalgebra and `Intrinsics`, as it was written before
    /// rows were moved all at once: the oracle of the row form.
    fn dense_check_one_by_one(
        from: &Thumb,
        to: &Thumb,
        to_from_from: &Isometry3<f64>,
        step: u32,
    ) -> DenseCounts {
        let mut c = DenseCounts::default();
        let (kf, kt) = (&from.intrinsics, &to.intrinsics);
        let tiles_across = from.width.div_ceil(LOCAL_TILE);
        let mut tiles =
            vec![[0.0f64; 6]; (tiles_across * from.height.div_ceil(LOCAL_TILE)) as usize];
        for r in (0..from.height).step_by(step as usize) {
            for col in (0..from.width).step_by(step as usize) {
                let Some(z) = from.depth_m(col, r) else {
                    continue;
                };
                c.valid += 1;
                let p = Point3::new(
                    (col as f64 - kf.cx) / kf.fx * z,
                    (r as f64 - kf.cy) / kf.fy * z,
                    z,
                );
                let q = Point3::from(
                    to_from_from.rotation.to_rotation_matrix() * p.coords
                        + to_from_from.translation.vector,
                );
                let Some((u, v)) = kt.project(&q).and_then(|uv| kt.pixel_of(&uv)) else {
                    continue;
                };
                let Some(zt) = to.depth_m(u, v) else { continue };
                c.inside += 1;
                if (zt - q.z).abs() <= depth_tolerance_m(q.z) {
                    c.agree += 1;
                    let a = from.gray[(r * from.width + col) as usize] as f64;
                    let b = to.gray[(v * to.width + u) as usize] as f64;
                    let t =
                        &mut tiles[((r / LOCAL_TILE) * tiles_across + col / LOCAL_TILE) as usize];
                    for (k, x) in [a, b, a * a, b * b, a * b].into_iter().enumerate() {
                        c.gray[k] += x;
                        t[k] += x;
                    }
                    t[5] += 1.0;
                } else if zt > q.z + depth_tolerance_m(q.z) {
                    c.violate += 1;
                }
            }
        }
        for t in tiles.iter().filter(|t| t[5] >= LOCAL_MIN_SAMPLES) {
            if let Some(r) = pearson(&[t[0], t[1], t[2], t[3], t[4]], t[5]) {
                c.local[0] += t[5] * r;
                c.local[1] += t[5];
            }
        }
        c
    }

    #[test]
    fn block_ranks_are_the_selected_ranks() {
        // Blocks of 16 (the ranking path) and of 9 and 25 (`select_nth_unstable`), every rank,
        // with ties: bit patterns of depths on a coarse grid, and invalid pixels as u32::MAX.
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for len in [9usize, 16, 25] {
            for _ in 0..300 {
                let v: Vec<u32> = (0..len)
                    .map(|_| {
                        x ^= x << 13;
                        x ^= x >> 7;
                        x ^= x << 17;
                        match x % 9 {
                            0 => u32::MAX,
                            k => (0.5 + k as f32 * 0.25).to_bits(),
                        }
                    })
                    .collect();
                let mut sorted = v.clone();
                sorted.sort_unstable();
                for m in 0..len {
                    assert_eq!(
                        rank_bits(&mut v.clone(), m),
                        sorted[m],
                        "{len} {m}: {sorted:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn rows_moved_at_once_count_exactly_as_one_sample_at_a_time() {
        let (rgb, depth, k) = wall_scene(0.0);
        let a = Thumb::new(&rgb, &depth, &k);
        let (rgb, depth, k) = wall_scene(0.23);
        let mut b = Thumb::new(&rgb, &depth, &k);
        // Holes and a ragged edge, so invalid samples and the borders are exercised.
        for i in (0..b.depth_mm.len()).step_by(7) {
            b.depth_mm[i] = 0;
        }
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut compared = 0;
        for trial in 0..200 {
            let pose = Isometry3::from_parts(
                Translation3::new(0.8 * uniform(), 0.8 * uniform(), 0.8 * uniform()),
                UnitQuaternion::from_euler_angles(
                    0.6 * uniform(),
                    0.6 * uniform(),
                    0.6 * uniform(),
                ),
            );
            for (from, to) in [(&a, &b), (&b, &a)] {
                for step in [1, 2, 3] {
                    let row_form = dense_check_every(from, to, &pose, step);
                    assert_eq!(
                        row_form,
                        dense_check_one_by_one(from, to, &pose, step),
                        "trial {trial}"
                    );
                    compared += usize::from(row_form.agree > 0);
                }
            }
        }
        assert!(compared > 400, "too few poses overlap: {compared}");
    }

    #[test]
    fn identity_agrees_and_a_wrong_pose_does_not() {
        let (rgb, depth, k) = wall_scene(0.0);
        let t = Thumb::new(&rgb, &depth, &k);
        assert_eq!((t.width, t.height), (64, 64));
        assert!((t.intrinsics.fx - 32.0).abs() < 1e-12);
        let same = dense_check_both(&t, &t, &Isometry3::identity());
        assert!(same.agree_share() > 0.99, "{same:?}");
        assert!(same.gray_correlation() > 0.99);
        // Pulled 0.5 m towards the scene: the query's surfaces now lie in front of the map's.
        let forward = Isometry3::from_parts(
            Translation3::new(0.0, 0.0, -0.5),
            UnitQuaternion::identity(),
        );
        let c = dense_check(&t, &t, &forward);
        assert!(c.agree_share() < 0.2 && c.violate_share() > 0.8, "{c:?}");
        // Slid 0.17 m along the wall: depth still agrees on the wall, grey does not.
        let slid = Isometry3::from_parts(
            Translation3::new(0.17, 0.0, 0.0),
            UnitQuaternion::identity(),
        );
        let c = dense_check(&t, &t, &slid);
        assert!(c.gray_correlation() < 0.5, "{}", c.gray_correlation());
    }

    #[test]
    fn tiles_keep_the_correlation_under_other_lighting() {
        let (rgb, depth, k) = wall_scene(0.0);
        let t = Thumb::new(&rgb, &depth, &k);
        // The near wall (columns < 100) lit by a dimmed lamp plus ambient light, the far one as
        // mapped: a gain and an offset per surface.
        let mut relit = rgb.data.clone();
        for (i, px) in relit.chunks_exact_mut(3).enumerate() {
            if (i as u32 % rgb.width) < 100 {
                for v in px {
                    *v = (0.3 * *v as f64 + 120.0) as u8;
                }
            }
        }
        let relit = RgbImage::new(rgb.width, rgb.height, relit).unwrap();
        let r = Thumb::new(&relit, &depth, &k);
        let c = dense_check_both(&r, &t, &Isometry3::identity());
        assert!(c.agree_share() > 0.99, "{c:?}");
        assert!(c.local_gray_correlation() > 0.95, "{c:?}");
        assert!(
            c.gray_correlation() < c.local_gray_correlation() - 0.1,
            "global {} local {}",
            c.gray_correlation(),
            c.local_gray_correlation()
        );
        // A pose slid along the wall keeps the depth but not the texture, tile by tile too.
        let slid = Isometry3::from_parts(
            Translation3::new(0.17, 0.0, 0.0),
            UnitQuaternion::identity(),
        );
        let c = dense_check(&r, &t, &slid);
        assert!(c.local_gray_correlation() < 0.5, "{c:?}");
        // Flat walls carry no texture: no tile counts, and the correlation is 0, not noise.
        let flat = RgbImage::new(rgb.width, rgb.height, vec![128; rgb.data.len()]).unwrap();
        let f = Thumb::new(&flat, &depth, &k);
        assert_eq!(
            dense_check(&f, &t, &Isometry3::identity()).local_gray_correlation(),
            0.0
        );
    }

    /// A fronto-parallel wall 1 m away filling the view, grey from `texture(x, y)` of its point
    /// (metres).
    fn flat_wall(texture: impl Fn(f64, f64) -> u8) -> Thumb {
        let k = Intrinsics::hpointloc();
        let (w, h) = (256u32, 256u32);
        let mut rgb = vec![0u8; (w * h * 3) as usize];
        for r in 0..h {
            for c in 0..w {
                let g = texture((c as f64 - k.cx) / k.fx, (r as f64 - k.cy) / k.fy);
                let i = (r * w + c) as usize * 3;
                rgb[i..i + 3].copy_from_slice(&[g, g, g]);
            }
        }
        let rgb = RgbImage::new(w, h, rgb).unwrap();
        let depth = DepthMap::from_metres(w, h, vec![1.0; (w * h) as usize]).unwrap();
        Thumb::new(&rgb, &depth, &k)
    }

    #[test]
    fn a_periodic_wall_has_aliases_and_a_random_one_has_none() {
        // Tiles of 0.17 m: the texture repeats every 0.34 m both ways.
        let tiles = flat_wall(|x, y| {
            let parity = ((x / 0.17).floor() + (y / 0.17).floor()) as i64;
            if parity.rem_euclid(2) == 0 {
                50
            } else {
                190
            }
        });
        let found = aliases(&tiles, &tiles, &Isometry3::identity());
        for d in found {
            // One or two periods (two still overlap the view by more than half).
            let periods = d / 0.34;
            assert!(
                d > 0.0 && (periods - periods.round()).abs() < 0.15,
                "{found:?}"
            );
        }
        // A texture without period (a hash of 5 cm cells): the estimate is the only fit.
        let random = flat_wall(|x, y| {
            let (a, b) = ((x / 0.05).floor() as i64, (y / 0.05).floor() as i64);
            let h = (a.wrapping_mul(73_856_093) ^ b.wrapping_mul(19_349_663)) as u64;
            (h.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 56) as u8
        });
        assert_eq!(
            aliases(&random, &random, &Isometry3::identity()),
            [0.0, 0.0]
        );
    }

    #[test]
    fn coverage_counts_cells() {
        assert_eq!(grid_coverage(&[[1.0, 1.0]], 256, 256, 4), 1.0 / 16.0);
        let all: Vec<[f32; 2]> = (0..16)
            .map(|i| [(i % 4) as f32 * 64.0 + 1.0, (i / 4) as f32 * 64.0 + 1.0])
            .collect();
        assert_eq!(grid_coverage(&all, 256, 256, 4), 1.0);
        assert_eq!(grid_coverage(&[[300.0, -5.0]], 256, 256, 4), 1.0 / 16.0);
    }
}
