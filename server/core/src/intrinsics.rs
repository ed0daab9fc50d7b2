//! Pinhole intrinsics in the OpenCV pixel convention (pixel (col, row) has its centre at (col, row)),
//! with optional lens distortion in the OpenCV / ROS `plumb_bob` model (k1, k2, p1, p2, k3).

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
    /// Lens distortion `[k1, k2, p1, p2, k3]` (OpenCV / ROS `plumb_bob`); all zero for an ideal
    /// pinhole. Maps written before distortion existed read as zero.
    #[serde(default)]
    pub distortion: [f64; 5],
}

/// Largest |coefficient| accepted for distortion: beyond it the model folds over inside the image.
pub const MAX_DISTORTION_COEFFICIENT: f64 = 10.0;

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
            distortion: [0.0; 5],
        }
    }

    /// A camera of `width` x `height` with the given horizontal and vertical fields of view (square
    /// pixels only when they agree with the aspect ratio), principal point at the image centre.
    pub fn from_fov_hv(width: u32, height: u32, hfov_deg: f64, vfov_deg: f64) -> Self {
        let fy = (height as f64 / 2.0) / (vfov_deg.to_radians() / 2.0).tan();
        Self {
            fy,
            ..Self::from_fov(width, height, hfov_deg)
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

    /// Whether any distortion coefficient is non-zero.
    pub fn is_distorted(&self) -> bool {
        self.distortion.iter().any(|&d| d != 0.0)
    }

    /// Check that the values describe a camera: finite, positive focal lengths, non-zero size, the
    /// principal point inside the image, distortion coefficients of at most
    /// [`MAX_DISTORTION_COEFFICIENT`] in magnitude.
    pub fn validate(&self) -> Result<(), IntrinsicsError> {
        let vals = [self.fx, self.fy, self.cx, self.cy];
        if vals.iter().chain(&self.distortion).any(|v| !v.is_finite()) {
            return Err(IntrinsicsError(format!("non-finite value in {self:?}")));
        }
        if let Some(d) = self
            .distortion
            .iter()
            .find(|d| d.abs() > MAX_DISTORTION_COEFFICIENT)
        {
            return Err(IntrinsicsError(format!(
                "distortion coefficient {d} is beyond +-{MAX_DISTORTION_COEFFICIENT}: not a plumb_bob lens"
            )));
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
        let (w, h) = (self.width as f64, self.height as f64);
        if !(-0.5..=w - 0.5).contains(&self.cx) || !(-0.5..=h - 0.5).contains(&self.cy) {
            return Err(IntrinsicsError(format!(
                "principal point ({}, {}) lies outside the {}x{} image (cx must be in -0.5..{}, cy in -0.5..{})",
                self.cx,
                self.cy,
                self.width,
                self.height,
                w - 0.5,
                h - 0.5
            )));
        }
        Ok(())
    }

    /// Apply the lens distortion to normalised image coordinates (x/z, y/z): where an ideal ray lands
    /// on the sensor, in normalised coordinates. Identity without distortion.
    pub fn distort_normalized(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Invert [`Intrinsics::distort_normalized`] by fixed-point iteration (the method OpenCV's
    /// `undistortPoints` uses), refined until the residual is below 1e-12 or 50 steps.
    pub fn undistort_normalized(&self, xd: f64, yd: f64) -> (f64, f64) {
        if !self.is_distorted() {
            return (xd, yd);
        }
        let [k1, k2, p1, p2, k3] = self.distortion;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            let (nx, ny) = ((xd - dx) / radial, (yd - dy) / radial);
            let done = (nx - x).abs() + (ny - y).abs() < 1e-12;
            (x, y) = (nx, ny);
            if done {
                break;
            }
        }
        (x, y)
    }

    /// The largest normalised radius sqrt((x/z)^2 + (y/z)^2) of a ray this lens images one to one:
    /// where the radial model `r * (1 + k1 r^2 + k2 r^4 + k3 r^6)` stops growing, the lens folds
    /// over and rays beyond land on the mirrored side. Infinite without such a fold (up to r = 10,
    /// 84 degrees off axis). Tangential terms are small and ignored here.
    pub fn lens_radius_limit(&self) -> f64 {
        let [k1, k2, _, _, k3] = self.distortion;
        if k1 == 0.0 && k2 == 0.0 && k3 == 0.0 {
            return f64::INFINITY;
        }
        let growth = |r: f64| {
            let r2 = r * r;
            1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
        };
        let mut r = 0.0;
        while r < 10.0 {
            r += 0.001;
            if growth(r) <= 0.0 {
                return r - 0.001;
            }
        }
        f64::INFINITY
    }

    /// The pixel (u, v) of this (possibly distorted) camera that sees the ray through normalised
    /// coordinates (x/z, y/z).
    pub fn pixel_of_ray(&self, x: f64, y: f64) -> (f64, f64) {
        let (xd, yd) = self.distort_normalized(x, y);
        (self.fx * xd + self.cx, self.fy * yd + self.cy)
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
    /// `None` outside, and for a non-finite coordinate.
    pub fn pixel_of(&self, uv: &Point2<f64>) -> Option<(u32, u32)> {
        // For x >= 0, truncation is the floor (and `floor` is a libm call on baseline x86-64).
        let (col, row) = (uv.x + 0.5, uv.y + 0.5);
        let inside =
            col >= 0.0 && row >= 0.0 && col < self.width as f64 && row < self.height as f64;
        inside.then_some((col as u32, row as u32))
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
    fn distortion_round_trips_and_matches_the_analytic_model() {
        let mut k = Intrinsics::from_fov(640, 480, 69.0);
        k.distortion = [-0.28, 0.07, 0.001, -0.0005, 0.0];
        // Analytic case: a pure radial k1 moves (0.3, 0) to 0.3 * (1 + k1 * 0.09).
        let mut radial = k;
        radial.distortion = [-0.2, 0.0, 0.0, 0.0, 0.0];
        let (xd, yd) = radial.distort_normalized(0.3, 0.0);
        assert!((xd - 0.3 * (1.0 - 0.2 * 0.09)).abs() < 1e-15 && yd == 0.0);
        // Tangential p1 alone shifts y by p1 * (r^2 + 2 y^2) and x by 2 p1 x y.
        radial.distortion = [0.0, 0.0, 0.01, 0.0, 0.0];
        let (xd, yd) = radial.distort_normalized(0.2, 0.1);
        assert!((xd - (0.2 + 2.0 * 0.01 * 0.02)).abs() < 1e-15);
        assert!((yd - (0.1 + 0.01 * (0.05 + 0.02))).abs() < 1e-15);
        for &(x, y) in &[(0.0, 0.0), (0.4, -0.3), (-0.55, 0.41), (0.1, 0.2)] {
            let (xd, yd) = k.distort_normalized(x, y);
            let (ux, uy) = k.undistort_normalized(xd, yd);
            assert!((ux - x).abs() < 1e-9 && (uy - y).abs() < 1e-9, "{x} {y}");
        }
        assert!(k.is_distorted() && !Intrinsics::hpointloc().is_distorted());
        k.validate().unwrap();
        // A barrel lens folds where d/dr of r * (1 + k1 r^2) is zero: r = sqrt(-1 / (3 k1)).
        let mut folded = k;
        folded.distortion = [-0.5, 0.0, 0.0, 0.0, 0.0];
        let r = folded.lens_radius_limit();
        assert!((r - (1.0f64 / 1.5).sqrt()).abs() < 2e-3, "{r}");
        assert!(Intrinsics::hpointloc().lens_radius_limit().is_infinite());
        k.distortion[0] = 50.0;
        assert!(k.validate().is_err());
    }

    #[test]
    fn bad_intrinsics_are_refused() {
        let mut k = Intrinsics::hpointloc();
        k.cx = 900.0;
        let e = k.validate().unwrap_err().0;
        assert!(
            e.contains("principal point") && e.contains("256x256"),
            "{e}"
        );
        let mut k = Intrinsics::hpointloc();
        k.fx = f64::NAN;
        assert!(k.validate().is_err());
        let mut k = Intrinsics::hpointloc();
        k.fy = -1.0;
        assert!(k.validate().is_err());
    }
}
