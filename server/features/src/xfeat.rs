//! XFeat (Potje et al., CVPR 2024): the CNN on ONNX Runtime, the sparse step here.
//!
//! The sparse step reproduces the upstream `detectAndCompute` exactly (checked against its saved
//! output by the parity test): 5x5 non-maximum suppression over the keypoint heatmap with threshold
//! 0.05, score = heatmap (nearest) x reliability (bilinear), top-k by score, descriptors sampled
//! bicubically (PyTorch `grid_sample`, zero padding, A = -0.75) and L2-normalised.

use std::path::Path;

use pntr_core::RgbImage;

use crate::runtime::{OnnxModel, RuntimeOptions};
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
}

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

impl XFeat {
    /// Load the backbone model (`models/xfeat_backbone.onnx`).
    pub fn load(path: &Path, params: XFeatParams) -> Result<Self, FeatureError> {
        let model = OnnxModel::load(
            path,
            &params.runtime,
            &["image"],
            &["feats", "heatmap", "reliability"],
        )?;
        Ok(Self { model, params })
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
        scored.truncate(self.params.top_k);
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
        let input = planar_rgb(image, rh, rw);
        let out = self.model.run(
            &[("image", vec![1, 3, rh, rw], &input)],
            &["feats", "heatmap", "reliability"],
        )?;
        let map = |i: usize| -> Result<Map, FeatureError> {
            let (s, d) = &out[i];
            if s.len() != 4 || s[0] != 1 || s.iter().product::<usize>() != d.len() {
                return Err(FeatureError::Inference(format!(
                    "unexpected output shape {s:?}"
                )));
            }
            Ok(Map {
                c: s[1],
                h: s[2],
                w: s[3],
                data: d,
            })
        };
        let (feats, heat, rel) = (map(0)?, map(1)?, map(2)?);
        if feats.c != XFEAT_DIM || (heat.h, heat.w) != (rh, rw) {
            return Err(FeatureError::Inference(format!(
                "outputs do not follow the XFeat contract: feats {} channels, heatmap {}x{}",
                feats.c, heat.h, heat.w
            )));
        }
        Ok(self.sparse(
            &feats,
            &heat,
            &rel,
            (w as f32 / rw as f32, h as f32 / rh as f32),
            (image.width, image.height),
        ))
    }

    fn name(&self) -> &'static str {
        "xfeat"
    }
}
