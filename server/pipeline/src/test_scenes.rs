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
    let (rgb, depth) = room_frame(
        room_from_camera,
        &Intrinsics::hpointloc(),
        k_per_m2,
        seed,
        &[],
    );
    Thumb::new(&rgb, &depth, &Intrinsics::hpointloc())
}

/// Boxes (min and max corners, room frame, metres) on the floor, walls and ceiling of
/// [`room_view`]'s room: detail smaller than a thumbnail's block, as a kitchen's cabinets and
/// appliances are for a VGA camera.
pub(crate) const CLUTTER: [([f64; 3], [f64; 3]); 8] = [
    ([-1.5, 0.6, 3.0], [-1.1, 1.2, 3.4]),
    ([0.5, 0.8, 2.5], [0.8, 1.2, 2.8]),
    ([-0.6, -0.8, 3.7], [-0.2, -0.4, 4.0]),
    ([0.9, -0.2, 3.8], [1.3, 0.1, 4.0]),
    ([1.7, -0.6, 1.5], [2.0, -0.2, 2.0]),
    ([-2.0, 0.0, 2.2], [-1.8, 0.3, 2.6]),
    ([-0.2, 0.9, 1.8], [0.1, 1.2, 2.1]),
    ([0.0, -1.5, 2.5], [0.4, -1.3, 2.9]),
];

/// The frame camera `k` at `room_from_camera` takes inside [`room_view`]'s room with `boxes` in
/// it (min and max corners, e.g. [`CLUTTER`]), with [`noisy_room_view`]'s depth noise: flat grey
/// colour and the depth.
pub(crate) fn room_frame(
    room_from_camera: &Isometry3<f64>,
    k: &Intrinsics,
    k_per_m2: f64,
    seed: u64,
    boxes: &[([f64; 3], [f64; 3])],
) -> (RgbImage, DepthMap) {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
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
            for (lo, hi) in boxes {
                // Slabs: the ray is inside the box between the largest entry and smallest exit.
                let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
                for a in 0..3 {
                    if d[a].abs() <= 1e-12 {
                        if o[a] < lo[a] || o[a] > hi[a] {
                            far = f64::NEG_INFINITY;
                        }
                        continue;
                    }
                    let (t0, t1) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
                    near = near.max(t0.min(t1));
                    far = far.min(t0.max(t1));
                }
                if near <= far && near > 1e-6 && near < best {
                    best = near;
                }
            }
            // `t` scales the camera ray whose z is 1, so it is the planar depth.
            let gauss =
                (-2.0 * uniform().ln()).sqrt() * (2.0 * std::f64::consts::PI * uniform()).cos();
            depth[(r * w + c) as usize] = (best + k_per_m2 * best * best * gauss) as f32;
        }
    }
    let rgb = RgbImage::new(w, h, vec![128; (w * h * 3) as usize]).unwrap();
    (rgb, DepthMap::from_metres(w, h, depth).unwrap())
}

/// A 40x30 thumbnail of a flat wall `depth_m` ahead, textured (a fixed pattern of grey levels) or
/// a uniform grey.
pub(crate) fn wall(depth_m: f64, textured: bool) -> Thumb {
    let (w, h) = (40u32, 30u32);
    Thumb {
        width: w,
        height: h,
        intrinsics: Intrinsics {
            fx: 35.0,
            fy: 35.0,
            cx: 19.5,
            cy: 14.5,
            width: w,
            height: h,
            distortion: [0.0; 5],
        },
        depth_mm: vec![(depth_m * 1000.0) as u16; (w * h) as usize],
        gray: (0..w * h)
            .map(|i| {
                if textured {
                    ((i * 37) % 251) as u8
                } else {
                    128
                }
            })
            .collect(),
    }
}
