//! Any camera to the map's: a query from another camera is resampled to the map's pixel scale before
//! feature extraction, and its keypoints are traced back to the query's own pixels for depth.
//!
//! Why: learned keypoint detectors and descriptors are only scale-tolerant within a factor of about
//! two, so a VGA robot camera (f about 470 px) against an HPointLoc map (f = 128 px) finds few correct
//! matches as it is. Resampling makes the query's pixels subtend the same angle as the map's.
//!
//! How, for a query camera K (optionally with `plumb_bob` distortion) and the map's focal length f:
//! 1. distortion, if any, is removed at the query's own resolution: every pixel of an ideal pinhole
//!    camera with K's numbers is sampled bilinearly where the distorted lens put that ray;
//! 2. the ideal image is resized per axis by `f / fx` and `f / fy` (non-square pixels become square)
//!    with a triangle filter whose support grows with the reduction, so downsampling does not alias
//!    (the `fast_image_resize` crate's SIMD convolution, about 10x the `image` crate's speed on a
//!    640x480 frame; pixel centres map as `(u' + 0.5) = (u + 0.5) * s`);
//! 3. depth is not interpolated for the keypoints: each keypoint's ray is traced back through the
//!    original, distorted camera to the query's own depth pixel, and the 3D point is that ray scaled to
//!    the measured planar depth. A nearest-neighbour depth image at the new scale is kept only for the
//!    dense verification thumbnails.
//!
//! A narrower camera sees less of the scene than the map's images do, so at the map's scale its image
//! holds fewer pixels and the extractor finds fewer keypoints. Such a query is resampled finer, so its
//! pixel count matches the map images', by at most [`MAX_FINER_SCALE`] above the map's focal length
//! (learned features tolerate that mismatch far better than the lost keypoints: on seed 3, a
//! 640x480 69-degree camera gained 0.68 -> 0.76 recall at (0.25 m, 2 deg), BENCHMARKS.md), and the
//! pipeline widens its retrieval shortlist by [`Resampled::coverage_ratio`].
//!
//! A query within 1% of the target focal length, as large as the map's images and without
//! distortion is used as it is.

use std::borrow::Cow;

use fast_image_resize::{FilterType, PixelType, ResizeAlg, ResizeOptions, Resizer};
use pntr_core::{DepthMap, Intrinsics, RgbImage};

use crate::pipeline::Query;

/// Relative focal-length difference below which a query is not resampled.
pub const SCALE_TOLERANCE: f64 = 0.01;
/// Smallest side of a resampled query, pixels (feature extractors need a few strides).
pub const MIN_RESAMPLED_SIDE: u32 = 64;
/// Largest side of a resampled query, pixels (upsampling beyond gives the extractor nothing new).
pub const MAX_RESAMPLED_SIDE: u32 = 2048;
/// Most a query smaller than the map's images (at the map's scale) is resampled beyond the map's
/// focal length, as a factor.
pub const MAX_FINER_SCALE: f64 = 1.5;

/// A query at the map's pixel scale, with the way back to the query's own pixels.
#[derive(Debug)]
pub struct Resampled<'a> {
    /// The query as an ideal pinhole camera at the map's focal length would see it (the original when
    /// nothing had to change).
    pub query: Cow<'a, Query>,
    /// The query as sent, when `query` is a resampled copy.
    source: Option<&'a Query>,
    /// The map images' pixel count over the query's at the map's focal length (1 when the query
    /// sees as much as a map image or more).
    pub coverage_ratio: f64,
}

impl<'a> Resampled<'a> {
    /// Whether the query was resampled (or undistorted).
    pub fn changed(&self) -> bool {
        self.source.is_some()
    }

    /// Back-project `keypoints` (pixels of [`Resampled::query`]) to 3D points in the query's OpenCV
    /// camera frame, metres, NaN where the depth under them is invalid. The depth is read at the
    /// keypoint's own pixel in the original frame (nearest), so resampling never blends depths across
    /// an edge.
    pub fn keypoint_points(&self, keypoints: &[[f32; 2]]) -> Vec<[f32; 3]> {
        let Some(src) = self.source else {
            return crate::map::keypoint_points(
                &self.query.intrinsics,
                &self.query.depth,
                None,
                keypoints,
            )
            .0;
        };
        let k = &self.query.intrinsics;
        let limit = src.intrinsics.lens_radius_limit();
        keypoints
            .iter()
            .map(|kp| {
                let (x, y) = ((kp[0] as f64 - k.cx) / k.fx, (kp[1] as f64 - k.cy) / k.fy);
                if x * x + y * y > limit * limit {
                    return [f32::NAN; 3];
                }
                let (u, v) = src.intrinsics.pixel_of_ray(x, y);
                match depth_near(&src.depth, u, v) {
                    Some(z) => [(x * z) as f32, (y * z) as f32, z as f32],
                    None => [f32::NAN; 3],
                }
            })
            .collect()
    }
}

fn depth_near(depth: &DepthMap, u: f64, v: f64) -> Option<f64> {
    let (c, r) = ((u + 0.5).floor(), (v + 0.5).floor());
    let inside = (0.0..depth.width as f64).contains(&c) && (0.0..depth.height as f64).contains(&r);
    if !inside {
        return None;
    }
    depth.get(c as u32, r as u32).map(f64::from)
}

/// Bring `q` to an ideal pinhole camera whose focal length is `focal_px` in both axes (the map's),
/// or finer when the query would hold fewer than `map_pixels` pixels there, as the module
/// documentation describes. Sizes are clamped to [`MIN_RESAMPLED_SIDE`] .. [`MAX_RESAMPLED_SIDE`]
/// (keeping the aspect ratio), so an extreme camera gets the nearest scale that still works.
pub fn to_map_scale(q: &Query, focal_px: f64, map_pixels: f64) -> Resampled<'_> {
    let k = &q.intrinsics;
    let (w, h) = (k.width as f64, k.height as f64);
    let at_map_scale = w * h * (focal_px / k.fx) * (focal_px / k.fy);
    let coverage_ratio = (map_pixels / at_map_scale).max(1.0);
    let focal_px = focal_px * coverage_ratio.sqrt().min(MAX_FINER_SCALE);
    let near = |f: f64| ((f - focal_px) / focal_px).abs() < SCALE_TOLERANCE;
    if !k.is_distorted() && near(k.fx) && near(k.fy) {
        return Resampled {
            query: Cow::Borrowed(q),
            source: None,
            coverage_ratio,
        };
    }
    let (mut sx, mut sy) = (focal_px / k.fx, focal_px / k.fy);
    let longest = (w * sx).max(h * sy);
    if longest > MAX_RESAMPLED_SIDE as f64 {
        let c = MAX_RESAMPLED_SIDE as f64 / longest;
        (sx, sy) = (sx * c, sy * c);
    }
    let shortest = (w * sx).min(h * sy);
    if shortest < MIN_RESAMPLED_SIDE as f64 {
        let c = MIN_RESAMPLED_SIDE as f64 / shortest;
        (sx, sy) = (sx * c, sy * c);
    }
    // The largest side wins over the smallest: a frame thinner than 2048:64 keeps a short side
    // below 64 rather than growing without bound.
    let longest = (w * sx).max(h * sy);
    if longest > MAX_RESAMPLED_SIDE as f64 {
        let c = MAX_RESAMPLED_SIDE as f64 / longest;
        (sx, sy) = (sx * c, sy * c);
    }
    let ow = ((w * sx).round() as u32).max(1);
    let oh = ((h * sy).round() as u32).max(1);
    // Exact scales after rounding the size, so pixel centres line up.
    let (sx, sy) = (ow as f64 / w, oh as f64 / h);
    let ideal = Intrinsics {
        distortion: [0.0; 5],
        ..*k
    };
    let rgb = if k.is_distorted() {
        undistort_rgb(&q.rgb, k)
    } else {
        q.rgb.clone()
    };
    let rgb = if (ow, oh) == (k.width, k.height) {
        rgb
    } else {
        resize_rgb(rgb, ow, oh)
    };
    let intrinsics = Intrinsics {
        fx: ideal.fx * sx,
        fy: ideal.fy * sy,
        cx: (ideal.cx + 0.5) * sx - 0.5,
        cy: (ideal.cy + 0.5) * sy - 0.5,
        width: ow,
        height: oh,
        distortion: [0.0; 5],
    };
    let mut depth = vec![0f32; (ow * oh) as usize];
    let limit = k.lens_radius_limit();
    for r in 0..oh {
        for c in 0..ow {
            let x = (c as f64 - intrinsics.cx) / intrinsics.fx;
            let y = (r as f64 - intrinsics.cy) / intrinsics.fy;
            if x * x + y * y > limit * limit {
                continue;
            }
            let (u, v) = k.pixel_of_ray(x, y);
            if let Some(z) = depth_near(&q.depth, u, v) {
                depth[(r * ow + c) as usize] = z as f32;
            }
        }
    }
    let depth = DepthMap::from_metres(ow, oh, depth).expect("sized above");
    Resampled {
        query: Cow::Owned(Query {
            rgb,
            depth,
            intrinsics,
        }),
        source: Some(q),
        coverage_ratio,
    }
}

/// `rgb` resized to `width` x `height` with a triangle (bilinear) filter whose support grows with
/// the reduction (antialiased downsampling).
pub fn resize_rgb(rgb: RgbImage, width: u32, height: u32) -> RgbImage {
    let (w, h) = (rgb.width, rgb.height);
    let src = fast_image_resize::images::Image::from_vec_u8(w, h, rgb.data, PixelType::U8x3)
        .expect("RgbImage holds width * height * 3 bytes");
    let mut dst = fast_image_resize::images::Image::new(width, height, PixelType::U8x3);
    Resizer::new()
        .resize(
            &src,
            &mut dst,
            &ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Bilinear)),
        )
        .expect("both images are U8x3 and non-empty");
    RgbImage::new(width, height, dst.into_vec()).expect("resize returns the requested size")
}

/// The image an ideal pinhole camera with `k`'s focal lengths and principal point would take, from
/// `rgb` taken through `k`'s distorted lens: bilinear samples at the distorted position of every
/// pixel's ray (black where that falls outside the frame or beyond the lens's fold,
/// [`Intrinsics::lens_radius_limit`]), same size.
pub fn undistort_rgb(rgb: &RgbImage, k: &Intrinsics) -> RgbImage {
    let (w, h) = (rgb.width as usize, rgb.height as usize);
    let mut out = vec![0u8; w * h * 3];
    let limit = k.lens_radius_limit();
    for r in 0..h {
        for c in 0..w {
            let (x, y) = ((c as f64 - k.cx) / k.fx, (r as f64 - k.cy) / k.fy);
            if x * x + y * y > limit * limit {
                continue;
            }
            let (u, v) = k.pixel_of_ray(x, y);
            let inside = (0.0..=(w - 1) as f64).contains(&u) && (0.0..=(h - 1) as f64).contains(&v);
            if !inside {
                continue;
            }
            let (u0, v0) = (u.floor() as usize, v.floor() as usize);
            let (u1, v1) = ((u0 + 1).min(w - 1), (v0 + 1).min(h - 1));
            let (fu, fv) = (u - u0 as f64, v - v0 as f64);
            for ch in 0..3 {
                let p = |cc: usize, rr: usize| rgb.data[(rr * w + cc) * 3 + ch] as f64;
                let top = p(u0, v0) * (1.0 - fu) + p(u1, v0) * fu;
                let bottom = p(u0, v1) * (1.0 - fu) + p(u1, v1) * fu;
                out[(r * w + c) * 3 + ch] = (top * (1.0 - fv) + bottom * fv).round() as u8;
            }
        }
    }
    RgbImage::new(rgb.width, rgb.height, out).expect("same size")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame of a fronto-parallel plane at `z` metres with a texture that is a function of the
    /// ray, seen through camera `k`.
    fn plane(k: &Intrinsics, z: f32) -> Query {
        let (w, h) = (k.width, k.height);
        let mut rgb = Vec::with_capacity((w * h * 3) as usize);
        for r in 0..h {
            for c in 0..w {
                let (xd, yd) = ((c as f64 - k.cx) / k.fx, (r as f64 - k.cy) / k.fy);
                let (x, y) = k.undistort_normalized(xd, yd);
                let g = (128.0 + 100.0 * (x * 9.0).sin() * (y * 7.0).cos()) as u8;
                rgb.extend_from_slice(&[g, g / 2, 255 - g]);
            }
        }
        Query {
            rgb: RgbImage::new(w, h, rgb).unwrap(),
            depth: DepthMap::from_metres(w, h, vec![z; (w * h) as usize]).unwrap(),
            intrinsics: *k,
        }
    }

    /// Where the 3D point of keypoint `kp` projects in the resampled image.
    fn reprojected(r: &Resampled, kp: [f32; 2]) -> nalgebra::Point2<f64> {
        let p = r.keypoint_points(&[kp])[0];
        r.query
            .intrinsics
            .project(&nalgebra::Point3::new(
                p[0] as f64,
                p[1] as f64,
                p[2] as f64,
            ))
            .unwrap()
    }

    #[test]
    fn same_scale_is_left_alone() {
        let q = plane(&Intrinsics::hpointloc(), 2.0);
        let r = to_map_scale(&q, 128.5, 65536.0);
        assert!(!r.changed());
        assert!(matches!(r.query, Cow::Borrowed(_)));
        assert_eq!(r.coverage_ratio, 1.0);
    }

    #[test]
    fn vga_query_comes_to_the_map_focal_and_keypoints_reach_the_right_depth() {
        let mut k = Intrinsics::from_fov(640, 480, 69.0);
        k.fy *= 1.05; // non-square pixels
        let q = plane(&k, 3.0);
        // Against a map of small images: the map's focal length exactly.
        let r = to_map_scale(&q, 128.0, 100.0);
        assert!(r.changed());
        let n = &r.query.intrinsics;
        assert!(
            (n.fx - 128.0).abs() < 0.5 && (n.fy - 128.0).abs() < 0.5,
            "{n:?}"
        );
        assert_eq!((n.width, n.height), (r.query.rgb.width, r.query.rgb.height));
        assert!(n.width < 200 && n.height < 160);
        // Against 256x256 map images the narrower view is resampled finer, at most 1.5x.
        let wide = to_map_scale(&q, 128.0, 65536.0);
        let nf = &wide.query.intrinsics;
        assert!(wide.coverage_ratio > 2.0, "{}", wide.coverage_ratio);
        assert!(
            (nf.fx - 192.0).abs() < 1.0 && (nf.fy - 192.0).abs() < 1.0,
            "{nf:?}"
        );
        // A keypoint at the resampled principal point sees straight ahead, at the plane's depth.
        let p = r.keypoint_points(&[[n.cx as f32, n.cy as f32]]);
        assert!(p[0][0].abs() < 1e-4 && p[0][1].abs() < 1e-4 && (p[0][2] - 3.0).abs() < 1e-6);
        // Any keypoint's 3D point projects back to where it was found in the resampled image.
        let back = reprojected(&r, [5.0, 7.0]);
        assert!(
            (back.x - 5.0).abs() < 1e-3 && (back.y - 7.0).abs() < 1e-3,
            "{back:?}"
        );
        assert!(r.query.depth.data.iter().all(|&d| d == 3.0));
    }

    #[test]
    fn undistortion_matches_the_ideal_camera() {
        // Analytic case: the same textured plane rendered through an ideal and a distorted lens; the
        // undistorted image must equal the ideal one away from the border.
        let ideal = Intrinsics::from_fov(320, 240, 80.0);
        let mut lens = ideal;
        lens.distortion = [-0.25, 0.06, 0.0008, -0.0006, 0.0];
        let truth = plane(&ideal, 2.0).rgb;
        let seen = plane(&lens, 2.0).rgb;
        let fixed = undistort_rgb(&seen, &lens);
        let (mut err, mut n, mut before) = (0.0, 0, 0.0);
        for r in 30..210 {
            for c in 40..280 {
                let i = ((r * 320 + c) * 3) as usize;
                err += (fixed.data[i] as f64 - truth.data[i] as f64).abs();
                before += (seen.data[i] as f64 - truth.data[i] as f64).abs();
                n += 1;
            }
        }
        let (err, before) = (err / n as f64, before / n as f64);
        assert!(err < 2.0, "mean error {err} grey levels after undistortion");
        assert!(
            before > 5.0 * err,
            "distortion was visible before: {before}"
        );
        // Through the resampler, keypoints trace back through the lens to the depth under them.
        let q = plane(&lens, 2.5);
        let r = to_map_scale(&q, 128.0, 1.0);
        assert!(r.changed());
        let back = reprojected(&r, [10.0, 12.0]);
        assert!((back.x - 10.0).abs() < 1e-3 && (back.y - 12.0).abs() < 1e-3);
    }

    #[test]
    fn rays_beyond_a_folding_lens_are_left_out() {
        // k1 = -0.5 folds at r = 0.816; a 120-degree view reaches r = 1.73 at its sides.
        let mut k = Intrinsics::from_fov(120, 120, 120.0);
        k.distortion = [-0.5, 0.0, 0.0, 0.0, 0.0];
        let q = plane(&k, 2.0);
        let out = undistort_rgb(&q.rgb, &k);
        assert_eq!(
            out.pixel(0, 0),
            [0, 0, 0],
            "a corner ray beyond the fold is black"
        );
        assert_ne!(out.pixel(60, 60), [0, 0, 0]);
        let r = to_map_scale(&q, 40.0, 1.0);
        let p = r.keypoint_points(&[[0.0, 0.0]]);
        assert!(p[0][0].is_nan(), "no depth for a ray beyond the fold");
    }

    #[test]
    fn extreme_cameras_are_clamped_to_workable_sizes() {
        let tele = Intrinsics::from_fov(800, 600, 5.0);
        let q = plane(&tele, 2.0);
        let r = to_map_scale(&q, 128.0, 65536.0);
        let n = &r.query.intrinsics;
        assert!(n.width.min(n.height) >= MIN_RESAMPLED_SIDE - 1, "{n:?}");
        // A hostile strip: 4096x1 may not grow past the largest side.
        let strip = Intrinsics::from_fov(4096, 1, 60.0);
        let q = plane(&strip, 2.0);
        let r = to_map_scale(&q, 128.0, 65536.0);
        let n = &r.query.intrinsics;
        assert!(
            n.width <= MAX_RESAMPLED_SIDE && n.height <= MAX_RESAMPLED_SIDE,
            "{n:?}"
        );
        let fish = Intrinsics::from_fov(64, 64, 170.0);
        let q = plane(&fish, 2.0);
        let r = to_map_scale(&q, 128.0, 65536.0);
        let n = &r.query.intrinsics;
        assert!(n.width.max(n.height) <= MAX_RESAMPLED_SIDE, "{n:?}");
    }
}
