//! ORB (FAST corners, Harris ranking, 8-level pyramid, rotated BRIEF) from `kornia-imgproc`: the
//! classical extractor, with no network, for the paper's classical baselines. Its 256-bit binary
//! descriptors are matched by [`crate::mnn::Mnn`] with Hamming distance.

use kornia_image::{Image, ImageSize};
use kornia_imgproc::features::OrbDetector;
use pntr_core::RgbImage;

use crate::{Extractor, FeatureError, Features};

/// The ORB extractor.
#[derive(Debug, Clone)]
pub struct Orb {
    /// Keypoints kept per image. Default 1024.
    pub top_k: usize,
}

impl Default for Orb {
    fn default() -> Self {
        Self { top_k: 1024 }
    }
}

impl Extractor for Orb {
    fn extract(&self, image: &RgbImage) -> Result<Features, FeatureError> {
        let (w, h) = (image.width as usize, image.height as usize);
        if w < 32 || h < 32 || image.data.len() != w * h * 3 {
            return Err(FeatureError::Input(format!(
                "ORB needs an RGB image of at least 32x32 with w*h*3 bytes, got {w}x{h} with {} bytes",
                image.data.len()
            )));
        }
        let gray: Vec<u8> = image
            .to_gray()
            .into_iter()
            .map(|v| (v + 0.5).min(255.0) as u8)
            .collect();
        let img = Image::<u8, 1>::new(
            ImageSize {
                width: w,
                height: h,
            },
            gray,
        )
        .map_err(|e| FeatureError::Input(e.to_string()))?;
        let det = OrbDetector {
            n_keypoints: self.top_k,
            ..OrbDetector::default()
        };
        let f = det
            .detect_and_extract_u8(&img)
            .map_err(|e| FeatureError::Inference(format!("ORB: {e}")))?;
        let n = f.keypoints_xy.len().min(self.top_k);
        Ok(Features {
            keypoints: f.keypoints_xy[..n].to_vec(),
            // ORB ranks by Harris response internally and does not return it: keep the order as score.
            scores: (0..n).map(|i| 1.0 - i as f32 / n.max(1) as f32).collect(),
            descriptors: Vec::new(),
            dim: 0,
            binary: f.descriptors[..n].to_vec(),
            image_size: (image.width, image.height),
        })
    }

    fn name(&self) -> &'static str {
        "orb"
    }
}
