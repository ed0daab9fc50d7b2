//! Depth from a separate depth camera, registered to the colour image.
//!
//! Many RGB-D cameras have two: a colour camera and a depth (infrared) camera a few centimetres
//! beside it, with its own lens. Raw Kinect frames (7-Scenes, 12-Scenes), RealSense recordings made
//! with `align_depth` off and many robots' bags keep the depth in the depth camera's pixels. pntr
//! needs the depth of each colour pixel, so such a depth image is registered here: every valid depth
//! pixel is back-projected with the depth camera's intrinsics (lens distortion removed), moved by
//! `colour_from_depth` and projected into the colour camera, keeping the nearest surface where several
//! land on one pixel (a z-buffer: the background never shows through a foreground edge). Where the
//! colour camera is magnified relative to the depth camera, each depth sample covers the colour
//! pixels of its footprint, so the registered image has no holes the sensor did not have.

use nalgebra::{Isometry3, Point3};
use pntr_core::{DepthMap, Intrinsics};

/// A depth camera apart from the colour camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthCamera {
    /// The depth camera's intrinsics (its image's size).
    pub intrinsics: Intrinsics,
    /// Takes a point in the depth camera's optical frame to the colour camera's (metres): the
    /// extrinsics a calibration gives as "depth to colour", and the TF `colour_optical <- depth_optical`.
    pub colour_from_depth: Isometry3<f64>,
}

/// `depth` (the depth camera's image, metres, 0 = none) as the colour camera `colour` would see it.
/// The result has the colour camera's size; a colour pixel no depth sample reaches is 0.
///
/// Errors: the depth image's size differs from the depth camera's (the likely mistake: the colour
/// camera's intrinsics given for the depth camera, or depth that is already registered).
pub fn register_depth(
    depth: &DepthMap,
    camera: &DepthCamera,
    colour: &Intrinsics,
) -> Result<DepthMap, String> {
    let k = &camera.intrinsics;
    if (depth.width, depth.height) != (k.width, k.height) {
        return Err(format!(
            "the depth image is {}x{} but the depth camera's intrinsics are for {}x{} (is the depth already registered to colour? then give no depth camera)",
            depth.width, depth.height, k.width, k.height
        ));
    }
    let (w, h) = (colour.width as usize, colour.height as usize);
    let mut out = vec![f32::INFINITY; w * h];
    // Footprint of one depth pixel in colour pixels (at equal range), rounded up.
    let magnify = (colour.fx / k.fx).max(colour.fy / k.fy);
    let half = ((magnify - 1.0) / 2.0).ceil().max(0.0) as i64;
    for r in 0..depth.height {
        for c in 0..depth.width {
            let Some(z) = depth.get(c, r) else { continue };
            let z = z as f64;
            let (x, y) = k.undistort_normalized((c as f64 - k.cx) / k.fx, (r as f64 - k.cy) / k.fy);
            let p = camera.colour_from_depth * Point3::new(x * z, y * z, z);
            if p.z <= 1e-3 {
                continue;
            }
            let (u, v) = colour.pixel_of_ray(p.x / p.z, p.y / p.z);
            let (uc, vc) = ((u + 0.5).floor() as i64, (v + 0.5).floor() as i64);
            for dv in -half..=half {
                for du in -half..=half {
                    let (cu, cv) = (uc + du, vc + dv);
                    if cu < 0 || cv < 0 || cu >= w as i64 || cv >= h as i64 {
                        continue;
                    }
                    let cell = &mut out[cv as usize * w + cu as usize];
                    if (p.z as f32) < *cell {
                        *cell = p.z as f32;
                    }
                }
            }
        }
    }
    for d in &mut out {
        if !d.is_finite() {
            *d = 0.0;
        }
    }
    DepthMap::from_metres(colour.width, colour.height, out).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn a_box_seen_by_both_cameras_lands_on_the_colour_pixels() {
        // A 585 px depth camera and a 525 px colour camera 2.5 cm to its side; a plane at 2 m with
        // a box 1.5 m away in its middle.
        let dk = Intrinsics {
            fx: 585.0,
            fy: 585.0,
            cx: 320.0,
            cy: 240.0,
            width: 640,
            height: 480,
            distortion: [0.0; 5],
        };
        let ck = Intrinsics {
            fx: 525.0,
            fy: 525.0,
            ..dk
        };
        let colour_from_depth = Isometry3::from_parts(
            Translation3::new(-0.025, 0.0, 0.002),
            UnitQuaternion::identity(),
        );
        // What the depth camera measures. In colour coordinates: a wall at z = 2 m and a box face
        // at 1.5 m for |x|, |y| < 0.2 m; a depth-camera point p is p + (-0.025, 0, 0.002) there.
        let mut d = vec![0f32; 640 * 480];
        for r in 0..480 {
            for c in 0..640 {
                let (x, y) = ((c as f64 - 320.0) / 585.0, (r as f64 - 240.0) / 585.0);
                let zd = 1.5 - 0.002;
                let on_box = (x * zd - 0.025).abs() < 0.2 && (y * zd).abs() < 0.2;
                d[r * 640 + c] = if on_box { zd } else { 2.0 - 0.002 } as f32;
            }
        }
        let depth = DepthMap::from_metres(640, 480, d).unwrap();
        let cam = DepthCamera {
            intrinsics: dk,
            colour_from_depth,
        };
        let reg = register_depth(&depth, &cam, &ck).unwrap();
        assert_eq!((reg.width, reg.height), (640, 480));
        // The box's centre seen by the colour camera: at 1.5 m.
        let centre = reg.get(320, 240).unwrap();
        assert!((centre - 1.5).abs() < 1e-3, "{centre}");
        // The colour pixel that sees the box's left edge at x = -0.2 m, 1.5 m: u = 320 - 0.2/1.5 525.
        let edge = 320.0 - 0.2 / 1.5 * 525.0;
        let inside = reg.get((edge + 3.0) as u32, 240).unwrap();
        let outside = reg.get((edge - 3.0) as u32, 240).unwrap();
        assert!((inside - 1.5).abs() < 1e-3, "inside {inside}");
        assert!((outside - 2.0).abs() < 1e-3, "outside {outside}");
        // No holes on the wall below the box (the depth camera's pixels are finer than colour's),
        // and beside the box only its parallax shadow: the strip of wall the colour camera sees
        // and the depth camera, 2.5 cm to the side, does not (0.025 * 525 * (1/1.5 - 1/2) = 2.2 px).
        let holes = (100..540).filter(|&c| reg.get(c, 400).is_none()).count();
        assert_eq!(holes, 0);
        let shadow = (100..540).filter(|&c| reg.get(c, 300).is_none()).count();
        assert!((1..=3).contains(&shadow), "{shadow} px of shadow");
        // A depth image of another size is named as the likely mistake.
        let small = DepthMap::from_metres(320, 240, vec![1.0; 320 * 240]).unwrap();
        let err = register_depth(&small, &cam, &ck).unwrap_err();
        assert!(
            err.contains("320x240") && err.contains("already registered"),
            "{err}"
        );
    }
}
