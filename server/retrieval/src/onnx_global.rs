//! A user-supplied global descriptor on ONNX Runtime (NetVLAD, MixVPR, SALAD, ... exported elsewhere).
//!
//! Contract (also in `models/README.md`): one input `image` [1, 3, H, W] float32, RGB, values 0..1,
//! channel-planar; one output `descriptor` [1, D] float32. H x W is the query's own size unless the
//! configuration names an input size, to which the image is resized bilinearly. The descriptor is
//! L2-normalised here, so the model need not do it. At load, the model is run once on a grey probe
//! image and a model whose output is not [1, D] (or not the configured D) is refused then, at start-up,
//! not at the first query.

use std::path::Path;

use pntr_core::RgbImage;
use pntr_features::runtime::{OnnxModel, RuntimeOptions};

use crate::RetrievalError;

/// A loaded global-descriptor model.
#[derive(Debug)]
pub struct OnnxGlobal {
    model: OnnxModel,
    input_size: Option<(u32, u32)>,
    dim: usize,
}

impl OnnxGlobal {
    /// Load `path`, probe it at `input_size` (or 256 x 256 when the model takes any size), and check its
    /// output is [1, D] with D = `expected_dim` when given.
    pub fn load(
        path: &Path,
        runtime: &RuntimeOptions,
        input_size: Option<(u32, u32)>,
        expected_dim: Option<usize>,
    ) -> Result<Self, RetrievalError> {
        let model = OnnxModel::load(path, runtime, &["image"], &["descriptor"])
            .map_err(|e| RetrievalError::Model(e.to_string()))?;
        let mut g = Self {
            model,
            input_size,
            dim: 0,
        };
        let (w, h) = input_size.unwrap_or((256, 256));
        let probe = RgbImage {
            width: w,
            height: h,
            data: vec![128; (w * h * 3) as usize],
        };
        let (shape, _) = g.raw(&probe)?;
        let bad = |m: String| RetrievalError::Model(format!("model {}: {m}", path.display()));
        if shape.len() != 2 || shape[0] != 1 || shape[1] == 0 {
            return Err(bad(format!(
                "output `descriptor` has shape {shape:?}; the contract is [1, D]"
            )));
        }
        if let Some(d) = expected_dim {
            if shape[1] != d {
                return Err(bad(format!(
                    "output `descriptor` has {} values; the configuration expects {d}",
                    shape[1]
                )));
            }
        }
        g.dim = shape[1];
        Ok(g)
    }

    /// Descriptor length D.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The model file.
    pub fn path(&self) -> &Path {
        self.model.path()
    }

    fn raw(&self, image: &RgbImage) -> Result<(Vec<usize>, Vec<f32>), RetrievalError> {
        let (w, h) = (image.width as usize, image.height as usize);
        if w == 0 || h == 0 || image.data.len() != w * h * 3 {
            return Err(RetrievalError::Input(format!(
                "RGB buffer of {} bytes for {w}x{h}",
                image.data.len()
            )));
        }
        let (ow, oh) = self
            .input_size
            .map(|(a, b)| (a as usize, b as usize))
            .unwrap_or((w, h));
        let planar = pntr_features::xfeat::planar_rgb(image, oh, ow);
        let mut out = self
            .model
            .run(&[("image", vec![1, 3, oh, ow], &planar)], &["descriptor"])
            .map_err(|e| RetrievalError::Model(e.to_string()))?;
        Ok(out.remove(0))
    }

    /// The L2-normalised descriptor of one image.
    pub fn describe(&self, image: &RgbImage) -> Result<Vec<f32>, RetrievalError> {
        let (shape, mut v) = self.raw(image)?;
        if shape != [1, self.dim] {
            return Err(RetrievalError::Model(format!(
                "model {}: output shape {shape:?} changed from [1, {}]",
                self.path().display(),
                self.dim
            )));
        }
        if v.iter().any(|x| !x.is_finite()) {
            return Err(RetrievalError::Model(format!(
                "model {}: the descriptor is not finite",
                self.path().display()
            )));
        }
        crate::l2_normalise(&mut v);
        Ok(v)
    }
}
