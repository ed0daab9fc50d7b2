//! Scenes for unit tests: what a camera sees inside a box room, as verification's thumbnails.

use nalgebra::{Isometry3, Vector3};
use pntr_core::{DepthMap, Intrinsics, RgbImage};

use crate::verify::Thumb;

/// The depth a camera at `room_from_camera` sees inside a box room (walls at x = +-2 m, floor at
/// y = 1.2 m below the origin, OpenCV axes with y down, back wall at z = 4 m, ceiling at y = -1.5 m).
pub(crate) fn room_view(room_from_camera: &Isometry3<f64>) -> Thumb {
    noisy_room_view(room_from_camera, 0.0, 0)
}

/// [`room_view`] seen by a depth sensor whose noise has a standard deviation of `k_per_m2 * z^2`
/// (seeded Gaussian draws per pixel, before the thumbnail's block median).
pub(crate) fn noisy_room_view(
    room_from_camera: &Isometry3<f64>,
    k_per_m2: f64,
    seed: u64,
) -> Thumb {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let k = Intrinsics::hpointloc();
    let (w, h) = (k.width, k.height);
    let mut depth = vec![0f32; (w * h) as usize];
    for r in 0..h {
        for c in 0..w {
            let ray_cam = Vector3::new((c as f64 - k.cx) / k.fx, (r as f64 - k.cy) / k.fy, 1.0);
            let o = room_from_camera.translation.vector;
            let d = room_from_camera.rotation * ray_cam;
            let mut best = f64::INFINITY;
            for (axis, plane) in [
                (0, -2.0),
                (0, 2.0),
                (1, 1.2),
                (1, -1.5),
                (2, 4.0),
                (2, -1.0),
            ] {
                if d[axis].abs() > 1e-9 {
                    let t = (plane - o[axis]) / d[axis];
                    if t > 1e-6 && t < best {
                        best = t;
                    }
                }
            }
            // `t` scales the camera ray whose z is 1, so it is the planar depth.
            let gauss =
                (-2.0 * uniform().ln()).sqrt() * (2.0 * std::f64::consts::PI * uniform()).cos();
            depth[(r * w + c) as usize] = (best + k_per_m2 * best * best * gauss) as f32;
        }
    }
    let rgb = RgbImage::new(w, h, vec![128; (w * h * 3) as usize]).unwrap();
    Thumb::new(&rgb, &DepthMap::from_metres(w, h, depth).unwrap(), &k)
}
