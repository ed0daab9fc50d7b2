//! Plain image containers: RGB, depth in metres, per-pixel labels. Row-major, no padding.
//!
//! Depth convention: a `DepthMap` holds planar (z) depth in metres with 0.0 meaning "no measurement".
//! Every decoder maps its own notion of invalid (0, NaN, infinity, negative, saturated far clip) to 0.0
//! here, so later stages test one thing: [`DepthMap::get`] returning `None`.

use crate::HPOINTLOC_DEPTH_SCALE_M;

/// Image buffers whose size does not match their dimensions.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{what}: expected {expected} values for {width}x{height}, got {got}")]
pub struct ImageError {
    /// Which buffer.
    pub what: &'static str,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Expected element count.
    pub expected: usize,
    /// Actual element count.
    pub got: usize,
}

fn check_len(
    what: &'static str,
    width: u32,
    height: u32,
    per_px: usize,
    got: usize,
) -> Result<(), ImageError> {
    let expected = width as usize * height as usize * per_px;
    if expected != got {
        return Err(ImageError {
            what,
            width,
            height,
            expected,
            got,
        });
    }
    Ok(())
}

/// An 8-bit RGB image, interleaved, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RgbImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height * 3` bytes, R G B per pixel.
    pub data: Vec<u8>,
}

impl RgbImage {
    /// Wrap a buffer, checking its length.
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self, ImageError> {
        check_len("rgb", width, height, 3, data.len())?;
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// The pixel at (col, row).
    pub fn pixel(&self, col: u32, row: u32) -> [u8; 3] {
        let i = (row as usize * self.width as usize + col as usize) * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// Luminance (Rec. 601) as f32 in 0..255, row-major: what keypoint extractors take.
    pub fn to_gray(&self) -> Vec<f32> {
        self.data.chunks_exact(3).map(luminance).collect()
    }
}

/// Luminance (0..255, ITU-R BT.601 weights) of one RGB pixel (`rgb[0..3]`), as [`RgbImage::to_gray`]
/// gives it.
#[inline]
pub fn luminance(rgb: &[u8]) -> f32 {
    0.299 * rgb[0] as f32 + 0.587 * rgb[1] as f32 + 0.114 * rgb[2] as f32
}

/// Planar depth in metres; 0.0 marks a pixel without a valid measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` depths in metres, 0.0 = invalid.
    pub data: Vec<f32>,
}

impl DepthMap {
    /// Depth in whole millimetres, row-major (the 16-bit unit of RGB-D cameras and ROS `16UC1`): 0 for
    /// invalid pixels, rounded, saturating at 65535 (65.5 m).
    pub fn to_millimetres(&self) -> Vec<u16> {
        self.data
            .iter()
            .map(|&d| {
                if d.is_finite() && d > 0.0 {
                    (d * 1000.0).round().min(65535.0) as u16
                } else {
                    0
                }
            })
            .collect()
    }

    /// Wrap metres, mapping every non-finite or non-positive value to "invalid".
    pub fn from_metres(width: u32, height: u32, mut data: Vec<f32>) -> Result<Self, ImageError> {
        check_len("depth", width, height, 1, data.len())?;
        for d in &mut data {
            if !d.is_finite() || *d <= 0.0 {
                *d = 0.0;
            }
        }
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Decode HPointLoc's normalised depth (0..1, 1 = 10 m).
    ///
    /// 0, negative and non-finite values are invalid. A value of 1.0 or more is the far clip of the
    /// renderer (anything at or beyond 10 m) rather than a measurement, so it is invalid too.
    pub fn from_hpointloc(width: u32, height: u32, normalised: &[f32]) -> Result<Self, ImageError> {
        check_len("depth", width, height, 1, normalised.len())?;
        let data = normalised
            .iter()
            .map(|&v| {
                if v.is_finite() && v > 0.0 && v < 1.0 {
                    v * HPOINTLOC_DEPTH_SCALE_M
                } else {
                    0.0
                }
            })
            .collect();
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// Encode to HPointLoc's normalised depth: metres / 10, clipped to 1.0, invalid as 0.
    pub fn to_hpointloc(&self) -> Vec<f32> {
        self.data
            .iter()
            .map(|&m| {
                if m > 0.0 {
                    (m / HPOINTLOC_DEPTH_SCALE_M).min(1.0)
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// The depth at (col, row) in metres, or `None` where it is invalid or outside the image.
    pub fn get(&self, col: u32, row: u32) -> Option<f32> {
        if col >= self.width || row >= self.height {
            return None;
        }
        let d = self.data[row as usize * self.width as usize + col as usize];
        (d > 0.0).then_some(d)
    }

    /// Number of pixels with a valid depth.
    pub fn valid_count(&self) -> usize {
        self.data.iter().filter(|&&d| d > 0.0).count()
    }
}

/// Per-pixel integer labels (instance ids), row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LabelMap {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` labels.
    pub data: Vec<u32>,
}

impl LabelMap {
    /// Wrap a buffer, checking its length.
    pub fn new(width: u32, height: u32, data: Vec<u32>) -> Result<Self, ImageError> {
        check_len("semantic", width, height, 1, data.len())?;
        Ok(Self {
            width,
            height,
            data,
        })
    }

    /// The label at (col, row).
    pub fn get(&self, col: u32, row: u32) -> u32 {
        self.data[row as usize * self.width as usize + col as usize]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hpointloc_depth_decoding_marks_invalid() {
        let d = DepthMap::from_hpointloc(3, 2, &[0.0, 0.25, f32::NAN, 1.0, -0.1, f32::INFINITY])
            .unwrap();
        assert_eq!(d.get(0, 0), None);
        assert_eq!(d.get(1, 0), Some(2.5));
        assert_eq!(d.get(2, 0), None);
        assert_eq!(d.get(0, 1), None, "far clip is not a measurement");
        assert_eq!(d.get(1, 1), None);
        assert_eq!(d.get(2, 1), None);
        assert_eq!(d.get(3, 0), None, "outside the image");
        assert_eq!(d.valid_count(), 1);
        let enc = d.to_hpointloc();
        assert_eq!(enc, vec![0.0, 0.25, 0.0, 0.0, 0.0, 0.0]);
    }

    #[test]
    fn sizes_are_checked() {
        assert!(RgbImage::new(2, 2, vec![0; 11]).is_err());
        assert!(DepthMap::from_metres(2, 2, vec![1.0; 3]).is_err());
        assert!(LabelMap::new(2, 2, vec![0; 4]).is_ok());
        let img = RgbImage::new(1, 1, vec![255, 0, 0]).unwrap();
        assert!((img.to_gray()[0] - 76.245).abs() < 1e-3);
    }
}
