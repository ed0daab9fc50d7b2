//! Pinhole intrinsics in the OpenCV pixel convention (pixel (col, row) has its centre at (col, row)).

use nalgebra::{Point2, Point3};

/// Pinhole camera intrinsics plus the image size they belong to.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (OpenCV convention).
    pub cx: f64,
    /// Principal point y, pixels (OpenCV convention).
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

/// Intrinsics that cannot describe a camera.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("invalid intrinsics: {0}")]
pub struct IntrinsicsError(pub String);

impl Intrinsics {
    /// The camera of a square image with the given horizontal field of view, principal point at the
    /// geometric image centre.
    pub fn from_fov(width: u32, height: u32, hfov_deg: f64) -> Self {
        let fx = (width as f64 / 2.0) / (hfov_deg.to_radians() / 2.0).tan();
        Self {
            fx,
            fy: fx,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
            width,
            height,
        }
    }

    /// HPointLoc's camera: 256 x 256, 90 degree field of view, fx = fy = 128.
    ///
    /// The principal point is 127.5, the exact centre of a symmetric frustum in the OpenCV convention
    /// used throughout pntr (the renderer shoots the ray of pixel `col` through u = col). The reference
    /// HPointLoc code uses 128 with the same convention, which puts every back-projected point half a
    /// pixel off; [`Intrinsics::hpointloc_reference`] reproduces that for legacy comparisons.
    pub fn hpointloc() -> Self {
        Self::from_fov(256, 256, 90.0)
    }

    /// The intrinsics the published HPointLoc code uses (cx = cy = 128), half a pixel off centre.
    pub fn hpointloc_reference() -> Self {
        Self {
            cx: 128.0,
            cy: 128.0,
            ..Self::hpointloc()
        }
    }

    /// Check that the values describe a camera: finite, positive focal lengths, non-zero size.
    pub fn validate(&self) -> Result<(), IntrinsicsError> {
        let vals = [self.fx, self.fy, self.cx, self.cy];
        if vals.iter().any(|v| !v.is_finite()) {
            return Err(IntrinsicsError(format!("non-finite value in {self:?}")));
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(IntrinsicsError(format!(
                "focal lengths must be positive, got fx={} fy={}",
                self.fx, self.fy
            )));
        }
        if self.width == 0 || self.height == 0 {
            return Err(IntrinsicsError("image size must be non-zero".into()));
        }
        Ok(())
    }

    /// Back-project pixel (u, v) with planar depth `z_m` to a point in the OpenCV camera frame.
    pub fn backproject(&self, u: f64, v: f64, z_m: f64) -> Point3<f64> {
        Point3::new(
            (u - self.cx) / self.fx * z_m,
            (v - self.cy) / self.fy * z_m,
            z_m,
        )
    }

    /// Project an OpenCV-frame point to pixel coordinates; `None` behind the camera.
    pub fn project(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        if p.z <= 1e-9 {
            return None;
        }
        Some(Point2::new(
            self.fx * p.x / p.z + self.cx,
            self.fy * p.y / p.z + self.cy,
        ))
    }

    /// The pixel (col, row) whose area contains (u, v), if it lies inside the image.
    pub fn pixel_of(&self, uv: &Point2<f64>) -> Option<(u32, u32)> {
        let col = (uv.x + 0.5).floor();
        let row = (uv.y + 0.5).floor();
        if col < 0.0 || row < 0.0 || col >= self.width as f64 || row >= self.height as f64 {
            return None;
        }
        Some((col as u32, row as u32))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hpointloc_defaults() {
        let k = Intrinsics::hpointloc();
        assert!((k.fx - 128.0).abs() < 1e-9 && (k.fy - 128.0).abs() < 1e-9);
        assert_eq!((k.cx, k.cy, k.width, k.height), (127.5, 127.5, 256, 256));
        let r = Intrinsics::hpointloc_reference();
        assert_eq!((r.cx, r.cy), (128.0, 128.0));
        k.validate().unwrap();
    }

    #[test]
    fn project_inverts_backproject() {
        let k = Intrinsics::hpointloc();
        let p = k.backproject(10.0, 200.0, 3.5);
        let uv = k.project(&p).unwrap();
        assert!((uv.x - 10.0).abs() < 1e-9 && (uv.y - 200.0).abs() < 1e-9);
        assert_eq!(k.pixel_of(&uv), Some((10, 200)));
        assert!(k.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn bad_intrinsics_are_refused() {
        let mut k = Intrinsics::hpointloc();
        k.fx = f64::NAN;
        assert!(k.validate().is_err());
        let mut k = Intrinsics::hpointloc();
        k.fy = -1.0;
        assert!(k.validate().is_err());
    }
}
