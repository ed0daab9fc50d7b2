//! XFeat (Potje et al., CVPR 2024): the CNN on ONNX Runtime, the sparse step here.
//!
//! The sparse step reproduces the upstream `detectAndCompute` exactly (checked against its saved
//! output by the parity test): 5x5 non-maximum suppression over the keypoint heatmap with threshold
//! 0.05, score = heatmap (nearest) x reliability (bilinear), top-k by score, descriptors sampled
//! bicubically (PyTorch `grid_sample`, zero padding, A = -0.75) and L2-normalised.
//!
//! The committed backbones are trimmed (`models/trim.py`): the graph takes the grey image (the mean
//! of the R, G and B planes) and ends before the keypoint softmax and the descriptors' L2
//! normalisation, which run here ([`heatmap_from_logits`], [`normalize_cells`]): ONNX Runtime spent
//! about a fifth of the backbone's time on one thread in those layout-bound steps. A backbone as
//! `torch.onnx.export` writes it in `models/export.py` before the trim (input `image`, outputs
//! `feats`, `heatmap`, `reliability`; the committed files before 63fe413) loads too.

use std::path::Path;

use pntr_core::RgbImage;

use crate::runtime::{OnnxModel, RuntimeOptions, Tensor};
use crate::{Extractor, FeatureError, Features};

/// XFeat settings.
#[derive(Debug, Clone, PartialEq)]
pub struct XFeatParams {
    /// Keep at most this many keypoints (highest score first). Default 1024.
    pub top_k: usize,
    /// Heatmap threshold for a keypoint. Default 0.05 (upstream).
    pub detection_threshold: f32,
    /// How the model runs.
    pub runtime: RuntimeOptions,
}

impl Default for XFeatParams {
    fn default() -> Self {
        Self {
            top_k: 1024,
            detection_threshold: 0.05,
            runtime: RuntimeOptions::default(),
        }
    }
}

/// The XFeat extractor.
#[derive(Debug)]
pub struct XFeat {
    model: OnnxModel,
    params: XFeatParams,
    layout: Layout,
}

/// Which graph a backbone file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Layout {
    /// `models/trim.py`'s: `gray` in; `descriptor_map`, `keypoint_logits`, `reliability` out.
    Trimmed,
    /// The graph as exported, before `models/trim.py`: `image` in; `feats`, `heatmap`,
    /// `reliability` out.
    Exported,
}

/// Input and output names of each [`Layout`], in the enum's order.
const LAYOUTS: [(&[&str], &[&str]); 2] = [
    (
        &["gray"],
        &["descriptor_map", "keypoint_logits", "reliability"],
    ),
    (&["image"], &["feats", "heatmap", "reliability"]),
];

/// Keypoint logits per cell of the backbone: 64 pixel positions of an 8 x 8 cell and a dustbin.
const LOGITS: usize = 65;

/// Descriptor length of XFeat.
pub const XFEAT_DIM: usize = 64;

/// A single-channel or multi-channel planar map.
struct Map<'a> {
    c: usize,
    h: usize,
    w: usize,
    data: &'a [f32],
}

impl Map<'_> {
    #[inline]
    fn at(&self, ch: usize, y: i64, x: i64) -> f32 {
        if x < 0 || y < 0 || x >= self.w as i64 || y >= self.h as i64 {
            0.0
        } else {
            self.data[(ch * self.h + y as usize) * self.w + x as usize]
        }
    }

    /// PyTorch grid_sample source coordinate (align_corners = False) of keypoint coordinate `p` given
    /// in an image of `size` pixels, via XFeat's normalisation 2 p / (size - 1) - 1.
    fn src(p: f32, size: usize, map: usize) -> f32 {
        let g = 2.0 * p / (size as f32 - 1.0) - 1.0;
        ((g + 1.0) * map as f32 - 1.0) / 2.0
    }
}

fn cubic1(x: f32, a: f32) -> f32 {
    ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
}

fn cubic2(x: f32, a: f32) -> f32 {
    ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a
}

fn cubic_weights(t: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    [
        cubic2(t + 1.0, A),
        cubic1(t, A),
        cubic1(1.0 - t, A),
        cubic2(2.0 - t, A),
    ]
}

/// Bilinear resize with PyTorch's `interpolate(mode='bilinear', align_corners=False)` sampling, planar
/// RGB in 0..1 out.
fn resize_planar(img: &RgbImage, oh: usize, ow: usize) -> Vec<f32> {
    let (w, h) = (img.width as usize, img.height as usize);
    let (sy, sx) = (h as f32 / oh as f32, w as f32 / ow as f32);
    let idx = |d: usize, scale: f32, n: usize| {
        let s = ((d as f32 + 0.5) * scale - 0.5).max(0.0);
        let i0 = (s.floor() as usize).min(n - 1);
        let i1 = (i0 + 1).min(n - 1);
        (i0, i1, s - i0 as f32)
    };
    let mut out = vec![0f32; 3 * oh * ow];
    for y in 0..oh {
        let (y0, y1, ty) = idx(y, sy, h);
        for x in 0..ow {
            let (x0, x1, tx) = idx(x, sx, w);
            for c in 0..3 {
                let p = |yy: usize, xx: usize| img.data[(yy * w + xx) * 3 + c] as f32 / 255.0;
                let top = p(y0, x0) * (1.0 - tx) + p(y0, x1) * tx;
                let bot = p(y1, x0) * (1.0 - tx) + p(y1, x1) * tx;
                out[(c * oh + y) * ow + x] = top * (1.0 - ty) + bot * ty;
            }
        }
    }
    out
}

/// Planar RGB in 0..1 at `oh` x `ow`: a straight conversion when the size matches, otherwise a
/// PyTorch-style bilinear resize.
pub fn planar_rgb(img: &RgbImage, oh: usize, ow: usize) -> Vec<f32> {
    let (w, h) = (img.width as usize, img.height as usize);
    if (oh, ow) != (h, w) {
        return resize_planar(img, oh, ow);
    }
    let mut planar = vec![0f32; 3 * h * w];
    for (i, px) in img.data.chunks_exact(3).enumerate() {
        for c in 0..3 {
            planar[c * h * w + i] = px[c] as f32 * (1.0 / 255.0);
        }
    }
    planar
}

/// The grey plane XFeat's network starts from, `oh` x `ow`: the mean of the planar R, G and B in
/// 0..1 ([`planar_rgb`]), added in that order and divided by 3, as the exported graph's `ReduceMean`.
pub fn gray_plane(img: &RgbImage, oh: usize, ow: usize) -> Vec<f32> {
    let (w, h) = (img.width as usize, img.height as usize);
    if (oh, ow) != (h, w) {
        let p = resize_planar(img, oh, ow);
        let n = oh * ow;
        return (0..n)
            .map(|i| (p[i] + p[n + i] + p[2 * n + i]) / 3.0)
            .collect();
    }
    let s = 1.0 / 255.0;
    img.data
        .chunks_exact(3)
        .map(|px| (px[0] as f32 * s + px[1] as f32 * s + px[2] as f32 * s) / 3.0)
        .collect()
}

/// XFeat's full-resolution keypoint heatmap, (8 h8) x (8 w8) row-major, from its keypoint logits
/// (planar, [`LOGITS`] x h8 x w8): the softmax over each cell's 65 logits, the dustbin dropped, the
/// 64 others laid out as the cell's 8 x 8 pixels (channel 8 a + b is the cell's row a, column b),
/// as upstream XFeat's `get_kpts_heatmap`. The logits are overwritten (with the softmax's
/// exponentials), which spares a frame-sized buffer.
pub fn heatmap_from_logits(logits: &mut [f32], h8: usize, w8: usize) -> Vec<f32> {
    let cells = h8 * w8;
    debug_assert_eq!(logits.len(), LOGITS * cells);
    let mut max = vec![f32::NEG_INFINITY; cells];
    for plane in logits.chunks_exact(cells) {
        for (m, &v) in max.iter_mut().zip(plane) {
            *m = m.max(v);
        }
    }
    let mut sum = vec![0f32; cells];
    for plane in logits.chunks_exact_mut(cells) {
        for k in 0..cells {
            let v = (plane[k] - max[k]).exp();
            plane[k] = v;
            sum[k] += v;
        }
    }
    let w = 8 * w8;
    let mut heat = vec![0f32; cells * 64];
    for (ch, plane) in logits.chunks_exact(cells).take(64).enumerate() {
        let (a, b) = (ch / 8, ch % 8);
        for i in 0..h8 {
            let row = &mut heat[(8 * i + a) * w..(8 * i + a + 1) * w];
            for j in 0..w8 {
                row[8 * j + b] = plane[i * w8 + j] / sum[i * w8 + j];
            }
        }
    }
    heat
}

/// Divide each cell's descriptor (planar, `channels` x `cells`) by its L2 norm (at least 1e-12, as
/// PyTorch's `F.normalize`), in place.
pub fn normalize_cells(data: &mut [f32], channels: usize, cells: usize) {
    debug_assert_eq!(data.len(), channels * cells);
    let mut norm = vec![0f32; cells];
    for plane in data.chunks_exact(cells) {
        for (n, &v) in norm.iter_mut().zip(plane) {
            *n += v * v;
        }
    }
    for n in &mut norm {
        *n = n.sqrt().max(1e-12);
    }
    for plane in data.chunks_exact_mut(cells) {
        for (v, &n) in plane.iter_mut().zip(&norm) {
            *v /= n;
        }
    }
}

impl XFeat {
    /// Load the backbone model (`models/xfeat_backbone.onnx`), trimmed (`models/trim.py`) or as
    /// exported. Errors: the file is missing, not loadable, or follows neither graph layout.
    pub fn load(path: &Path, params: XFeatParams) -> Result<Self, FeatureError> {
        let (model, i) = OnnxModel::load_layout(path, &params.runtime, &LAYOUTS)?;
        let layout = [Layout::Trimmed, Layout::Exported][i];
        Ok(Self {
            model,
            params,
            layout,
        })
    }

    /// The execution provider in use.
    pub fn provider(&self) -> &'static str {
        self.model.provider()
    }

    /// The settings in use.
    pub fn params(&self) -> &XFeatParams {
        &self.params
    }

    fn sparse(
        &self,
        feats: &Map,
        heat: &Map,
        rel: &Map,
        scale: (f32, f32),
        image_size: (u32, u32),
        top_k: usize,
    ) -> Features {
        let (hh, hw) = (heat.h, heat.w);
        let th = self.params.detection_threshold;
        // Non-maximum suppression in a 5x5 window (max-pool with -inf padding), row-major order.
        let mut cand: Vec<(usize, usize)> = Vec::new();
        for y in 0..hh {
            for x in 0..hw {
                let v = heat.data[y * hw + x];
                if v <= th {
                    continue;
                }
                let mut is_max = true;
                'w: for yy in y.saturating_sub(2)..(y + 3).min(hh) {
                    for xx in x.saturating_sub(2)..(x + 3).min(hw) {
                        if heat.data[yy * hw + xx] > v {
                            is_max = false;
                            break 'w;
                        }
                    }
                }
                if is_max {
                    cand.push((x, y));
                }
            }
        }
        let mut scored: Vec<(f32, usize, usize)> = cand
            .into_iter()
            .map(|(x, y)| {
                if x == 0 && y == 0 {
                    // Upstream marks (0, 0) as padding and gives it score -1.
                    return (-1.0, x, y);
                }
                let nx = Map::src(x as f32, hw, hw).round_ties_even() as i64;
                let ny = Map::src(y as f32, hh, hh).round_ties_even() as i64;
                let near = heat.at(0, ny, nx);
                let (sx, sy) = (Map::src(x as f32, hw, rel.w), Map::src(y as f32, hh, rel.h));
                let (x0, y0) = (sx.floor(), sy.floor());
                let (tx, ty) = (sx - x0, sy - y0);
                let (x0, y0) = (x0 as i64, y0 as i64);
                let bil = rel.at(0, y0, x0) * (1.0 - tx) * (1.0 - ty)
                    + rel.at(0, y0, x0 + 1) * tx * (1.0 - ty)
                    + rel.at(0, y0 + 1, x0) * (1.0 - tx) * ty
                    + rel.at(0, y0 + 1, x0 + 1) * tx * ty;
                (near * bil, x, y)
            })
            .collect();
        // Highest score first; ties keep row-major order.
        scored.sort_by(|a, b| b.0.total_cmp(&a.0));
        scored.truncate(top_k);
        scored.retain(|s| s.0 > 0.0);
        let mut keypoints = Vec::with_capacity(scored.len());
        let mut scores = Vec::with_capacity(scored.len());
        let mut descriptors = Vec::with_capacity(scored.len() * XFEAT_DIM);
        // The feature map with the channels of each cell side by side (h x w x c), so each of a
        // keypoint's 16 taps adds to all channels at once (vectorised). Per channel the sum runs over
        // the taps in the same order as one channel at a time, so the descriptors are the same.
        let (fc, fh, fw) = (feats.c, feats.h, feats.w);
        let mut cells = vec![0f32; fc * fh * fw];
        for c in 0..fc {
            for (k, &v) in feats.data[c * fh * fw..(c + 1) * fh * fw]
                .iter()
                .enumerate()
            {
                cells[k * fc + c] = v;
            }
        }
        let mut v = vec![0f32; fc];
        for &(s, x, y) in &scored {
            let (sx, sy) = (Map::src(x as f32, hw, fw), Map::src(y as f32, hh, fh));
            let (x0, y0) = (sx.floor(), sy.floor());
            let (wx, wy) = (cubic_weights(sx - x0), cubic_weights(sy - y0));
            let (x0, y0) = (x0 as i64, y0 as i64);
            let start = descriptors.len();
            v.fill(0.0);
            for (j, wyj) in wy.iter().enumerate() {
                for (i, wxi) in wx.iter().enumerate() {
                    let (yy, xx) = (y0 - 1 + j as i64, x0 - 1 + i as i64);
                    // Zero padding: a tap outside the map adds nothing.
                    if xx < 0 || yy < 0 || xx >= fw as i64 || yy >= fh as i64 {
                        continue;
                    }
                    let w = wyj * wxi;
                    let cell = (yy as usize * fw + xx as usize) * fc;
                    for (acc, &f) in v.iter_mut().zip(&cells[cell..cell + fc]) {
                        *acc += w * f;
                    }
                }
            }
            descriptors.extend_from_slice(&v);
            let norm = descriptors[start..]
                .iter()
                .map(|v| v * v)
                .sum::<f32>()
                .sqrt()
                .max(1e-12);
            for v in &mut descriptors[start..] {
                *v /= norm;
            }
            keypoints.push([x as f32 * scale.0, y as f32 * scale.1]);
            scores.push(s);
        }
        Features {
            keypoints,
            scores,
            descriptors,
            dim: XFEAT_DIM,
            binary: Vec::new(),
            image_size,
        }
    }
}

impl Extractor for XFeat {
    fn extract(&self, image: &RgbImage) -> Result<Features, FeatureError> {
        self.extract_at_most(image, self.params.top_k)
    }

    fn extract_at_most(&self, image: &RgbImage, top_k: usize) -> Result<Features, FeatureError> {
        let top_k = top_k.min(self.params.top_k);
        let (w, h) = (image.width as usize, image.height as usize);
        if w < 32 || h < 32 {
            return Err(FeatureError::Input(format!(
                "image {w}x{h} is smaller than 32x32"
            )));
        }
        if image.data.len() != w * h * 3 {
            return Err(FeatureError::Input(format!(
                "RGB buffer has {} bytes, {w}x{h}x3 needs {}",
                image.data.len(),
                w * h * 3
            )));
        }
        let (rh, rw) = (h / 32 * 32, w / 32 * 32);
        let shape_of = |out: &[Tensor], i: usize| -> Result<[usize; 3], FeatureError> {
            let (s, d) = &out[i];
            if s.len() != 4 || s[0] != 1 || s.iter().product::<usize>() != d.len() {
                return Err(FeatureError::Inference(format!(
                    "unexpected output shape {s:?}"
                )));
            }
            Ok([s[1], s[2], s[3]])
        };
        let contract = |what: String| {
            FeatureError::Inference(format!("outputs do not follow the XFeat contract: {what}"))
        };
        let (feats, f, heat, rel): (Vec<f32>, [usize; 3], Vec<f32>, Tensor) = match self.layout {
            Layout::Exported => {
                let input = planar_rgb(image, rh, rw);
                let mut out = self.model.run(
                    &[("image", vec![1, 3, rh, rw], &input)],
                    &["feats", "heatmap", "reliability"],
                )?;
                let (f, hm, r) = (shape_of(&out, 0)?, shape_of(&out, 1)?, shape_of(&out, 2)?);
                if f[0] != XFEAT_DIM || hm != [1, rh, rw] || r != [1, f[1], f[2]] {
                    return Err(contract(format!(
                        "feats {f:?}, heatmap {hm:?}, reliability {r:?} (channels, rows, columns) for a {rh}x{rw} input"
                    )));
                }
                let rel = out.pop().expect("three outputs");
                let heat = out.pop().expect("three outputs").1;
                (out.pop().expect("three outputs").1, f, heat, rel)
            }
            Layout::Trimmed => {
                let input = gray_plane(image, rh, rw);
                let mut out = self.model.run(
                    &[("gray", vec![1, 1, rh, rw], &input)],
                    &["descriptor_map", "keypoint_logits", "reliability"],
                )?;
                let (f, l, r) = (shape_of(&out, 0)?, shape_of(&out, 1)?, shape_of(&out, 2)?);
                let cells = [rh / 8, rw / 8];
                if f != [XFEAT_DIM, cells[0], cells[1]]
                    || l != [LOGITS, cells[0], cells[1]]
                    || r != [1, cells[0], cells[1]]
                {
                    return Err(contract(format!(
                        "descriptor map {f:?}, keypoint logits {l:?}, reliability {r:?} (channels, rows, columns) for a {rh}x{rw} input"
                    )));
                }
                let rel = out.pop().expect("three outputs");
                let heat =
                    heatmap_from_logits(&mut out.pop().expect("three outputs").1, l[1], l[2]);
                let mut feats = out.pop().expect("three outputs").1;
                normalize_cells(&mut feats, f[0], f[1] * f[2]);
                (feats, f, heat, rel)
            }
        };
        let feats = Map {
            c: f[0],
            h: f[1],
            w: f[2],
            data: &feats,
        };
        let heat = Map {
            c: 1,
            h: rh,
            w: rw,
            data: &heat,
        };
        let rel = Map {
            c: rel.0[1],
            h: rel.0[2],
            w: rel.0[3],
            data: &rel.1,
        };
        Ok(self.sparse(
            &feats,
            &heat,
            &rel,
            (w as f32 / rw as f32, h as f32 / rh as f32),
            (image.width, image.height),
            top_k,
        ))
    }

    fn name(&self) -> &'static str {
        "xfeat"
    }

    fn engine(&self) -> &'static str {
        self.model.provider()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_heatmap_puts_each_logit_at_its_pixel_of_the_cell() {
        // 2 x 3 cells; in each, one logit far above the others, at a channel that depends on the cell.
        let (h8, w8) = (2, 3);
        let cells = h8 * w8;
        let mut logits = vec![0f32; LOGITS * cells];
        let channel = |k: usize| (k * 11 + 5) % 64;
        for k in 0..cells {
            logits[channel(k) * cells + k] = 30.0;
        }
        let heat = heatmap_from_logits(&mut logits, h8, w8);
        assert_eq!(heat.len(), 64 * cells);
        for k in 0..cells {
            let (i, j) = (k / w8, k % w8);
            let (a, b) = (channel(k) / 8, channel(k) % 8);
            let peak = heat[(8 * i + a) * 8 * w8 + 8 * j + b];
            assert!(peak > 0.999, "cell {k}: {peak}");
        }
        // Softmax over 65 with the dustbin: each cell's 64 pixels sum to 1 minus the dustbin's share.
        let uniform = heatmap_from_logits(&mut vec![0f32; LOGITS * cells], h8, w8);
        assert!(uniform.iter().all(|&v| (v - 1.0 / 65.0).abs() < 1e-7));
    }

    #[test]
    fn cells_come_out_unit_length_and_a_zero_cell_stays_zero() {
        let cells = 3;
        let mut d: Vec<f32> = (0..4 * cells).map(|i| (i % 5) as f32 - 1.0).collect();
        for c in 0..4 {
            d[c * cells + 2] = 0.0;
        }
        normalize_cells(&mut d, 4, cells);
        for k in 0..2 {
            let n: f32 = (0..4).map(|c| d[c * cells + k].powi(2)).sum();
            assert!((n - 1.0).abs() < 1e-6, "cell {k}: {n}");
        }
        assert!((0..4).all(|c| d[c * cells + 2] == 0.0));
    }

    #[test]
    fn the_grey_plane_is_the_mean_of_the_colour_planes() {
        let img = RgbImage::new(
            32,
            32,
            (0..32 * 32 * 3).map(|i| (i * 7 % 256) as u8).collect(),
        )
        .unwrap();
        let g = gray_plane(&img, 32, 32);
        let p = planar_rgb(&img, 32, 32);
        let n = 32 * 32;
        for i in 0..n {
            let want = (p[i] + p[n + i] + p[2 * n + i]) / 3.0;
            assert!((g[i] - want).abs() <= 1e-7, "{i}: {} vs {want}", g[i]);
        }
    }
}
