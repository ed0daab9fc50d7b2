//! Is a frame's depth registered to its colour image? Where the depth jumps (an object's outline
//! against what lies behind it) the colour image has an edge too, at the same pixels when the two
//! are registered. A separate depth camera's image used as it is (its own focal length, a few
//! centimetres beside the colour camera) puts those outlines elsewhere: shifted, and stretched
//! about the centre where the two focal lengths differ (7-Scenes' raw Kinect depth against its
//! colour: about 6 px shifted and 30 px stretched at the borders of a 640x480 frame).
//!
//! The measure: the colour gradient's mean at the depth jumps' pixels, displaced by every offset
//! within a window; the offset of the largest mean is where the depth's outlines meet the colour
//! edges, taken separately on the frame's left and right thirds, so a stretch shows as two offsets
//! of opposite sign. (The same idea as the edge alignment that RGB-D calibration tools score; a
//! search over image shifts is enough to name the mistake, not to calibrate.)

use pntr_core::{DepthMap, RgbImage};

/// The offsets searched, pixels either way, at 640 px of width (scaled with the width).
pub const SEARCH_PX_AT_VGA: f64 = 24.0;
/// A depth jump: neighbouring depths that differ by more than this (metres) plus
/// [`JUMP_RANGE_SHARE`] of the nearer one.
pub const JUMP_M: f32 = 0.1;
/// See [`JUMP_M`].
pub const JUMP_RANGE_SHARE: f32 = 0.05;
/// Depth jumps a third needs for its offset to count, at 640 px of width (scaled with the width,
/// as outlines are; at least 50).
pub const MIN_JUMPS_AT_VGA: usize = 200;
/// An offset counts only where its score beats the score without offset by this factor.
pub const MIN_GAIN: f64 = 1.15;
/// Offsets of at least this many pixels at 640 px of width (scaled with the width) name a
/// shift where both thirds are off alike by this much: rendered depth measures 0-1 px; 7-Scenes'
/// Kinect depth registered with its translation offset alone 1-6 px on the left third and up to
/// 16 on the right (not alike, so not named); the same depth used unregistered, its 585 px focal
/// length taken for the colour camera's 525, 14-16 px on each third (a stretch).
pub const MISREGISTERED_PX_AT_VGA: f64 = 12.0;
/// Horizontal offsets of opposite signs in the two thirds, each at least this many pixels at 640
/// px of width, name a stretch: a depth lens whose focal length differs by 4% or more (the thirds'
/// middles lie about 210 px from the centre). Registered depth never shows the pattern (rendered:
/// 0-1 px; 7-Scenes: one third within 4 px).
pub const STRETCHED_PX_AT_VGA: f64 = 8.0;

/// Where a frame's depth outlines meet its colour edges: the best offset of the left and right
/// thirds (pixels, `[dx, dy]`: depth outline + offset = colour edge), `None` for a third with too
/// few depth jumps or no clear best.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Alignment {
    /// The frame's left third.
    pub left: Option<[i32; 2]>,
    /// The frame's right third.
    pub right: Option<[i32; 2]>,
    /// The frame's width, pixels.
    pub width: u32,
}

/// Measure a frame ([`Alignment`]). `rgb` and `depth` of one size; anything else gives no offset.
pub fn measure(rgb: &RgbImage, depth: &DepthMap) -> Alignment {
    let (w, h) = (rgb.width as usize, rgb.height as usize);
    let none = Alignment {
        left: None,
        right: None,
        width: rgb.width,
    };
    if (depth.width, depth.height) != (rgb.width, rgb.height) || w < 32 || h < 32 {
        return none;
    }
    let grey: Vec<f32> = rgb
        .data
        .chunks_exact(3)
        .map(|p| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32)
        .collect();
    // Colour gradient magnitude (central differences), 0 on the border.
    let mut grad = vec![0f32; w * h];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let gx = grey[y * w + x + 1] - grey[y * w + x - 1];
            let gy = grey[(y + 1) * w + x] - grey[(y - 1) * w + x];
            grad[y * w + x] = gx.abs() + gy.abs();
        }
    }
    // Depth jumps: the pixel on the near side of a clear discontinuity.
    let d = &depth.data;
    let valid = |v: f32| v.is_finite() && v > 0.0;
    let mut jumps: Vec<(usize, usize)> = Vec::new();
    for y in 0..h - 1 {
        for x in 0..w - 1 {
            let a = d[y * w + x];
            for b_at in [(x + 1, y), (x, y + 1)] {
                let b = d[b_at.1 * w + b_at.0];
                if valid(a) && valid(b) && (a - b).abs() > JUMP_M + JUMP_RANGE_SHARE * a.min(b) {
                    jumps.push(if a < b { (x, y) } else { b_at });
                }
            }
        }
    }
    let r = (SEARCH_PX_AT_VGA * w as f64 / 640.0).round().max(2.0) as i32;
    let best = |lo: usize, hi: usize| -> Option<[i32; 2]> {
        let at: Vec<(usize, usize)> = jumps
            .iter()
            .copied()
            .filter(|&(x, _)| x >= lo && x < hi)
            .collect();
        if at.len() < (MIN_JUMPS_AT_VGA * w / 640).max(50) {
            return None;
        }
        let score = |dx: i32, dy: i32| -> f64 {
            let (mut sum, mut n) = (0f64, 0usize);
            for &(x, y) in &at {
                let (u, v) = (x as i32 + dx, y as i32 + dy);
                if u >= 0 && v >= 0 && (u as usize) < w && (v as usize) < h {
                    sum += grad[v as usize * w + u as usize] as f64;
                    n += 1;
                }
            }
            if n * 2 < at.len() {
                0.0
            } else {
                sum / n as f64
            }
        };
        let zero = score(0, 0);
        let mut top = ([0, 0], zero);
        for dy in -r..=r {
            for dx in -r..=r {
                let s = score(dx, dy);
                if s > top.1 {
                    top = ([dx, dy], s);
                }
            }
        }
        // No clear best (a frame without texture at its outlines): the offset is not measured.
        (top.0 == [0, 0] || top.1 >= MIN_GAIN * zero).then_some(top.0)
    };
    Alignment {
        left: best(0, w / 3),
        right: best(w - w / 3, w),
        width: rgb.width,
    }
}

/// What frames measured with [`measure`] say together, from the median offset of each third (over
/// the frames that measured it, at least 3 each; pixels scaled to 640 px of width): `Some(message)`
/// naming the likely mistake when the two show a lens's stretch (horizontal offsets of opposite
/// signs, each at least [`STRETCHED_PX_AT_VGA`]) or a camera's offset (both at least
/// [`MISREGISTERED_PX_AT_VGA`], and alike); `None` otherwise, or when too few frames measured.
pub fn misregistration_hint(frames: &[Alignment]) -> Option<String> {
    let width = frames.first()?.width;
    let median_of = |side: &dyn Fn(&Alignment) -> Option<[i32; 2]>| -> Option<[i32; 2]> {
        let got: Vec<[i32; 2]> = frames.iter().filter_map(side).collect();
        if got.len() < 3 {
            return None;
        }
        let mid = |k: usize| {
            let mut v: Vec<i32> = got.iter().map(|o| o[k]).collect();
            v.sort_unstable();
            v[v.len() / 2]
        };
        Some([mid(0), mid(1)])
    };
    let left = median_of(&|a| a.left)?;
    let right = median_of(&|a| a.right)?;
    let measured = frames
        .iter()
        .filter(|a| a.left.is_some() || a.right.is_some())
        .count();
    // Pixels at 640 px of width.
    let vga = |px: i32| px as f64 * 640.0 / width as f64;
    let norm = |o: [i32; 2]| vga(o[0]).hypot(vga(o[1]));
    let (t, gap) = (
        MISREGISTERED_PX_AT_VGA,
        [left[0] - right[0], left[1] - right[1]],
    );
    let ts = STRETCHED_PX_AT_VGA;
    // A longer (shorter) depth lens: outlines outside (inside) the colour edges on both sides.
    let stretched = (vga(left[0]) >= ts && vga(right[0]) <= -ts)
        || (vga(left[0]) <= -ts && vga(right[0]) >= ts);
    // A depth camera beside the colour camera: both thirds moved alike.
    let shifted =
        norm(left) >= t && norm(right) >= t && norm(gap) <= 0.5 * norm(left).max(norm(right));
    let how = if stretched {
        "stretched about the centre (a depth camera with another focal length)"
    } else if shifted {
        "shifted (a depth camera beside the colour camera)"
    } else {
        // Offsets that differ between the thirds without a lens's or an offset's pattern: what a
        // real sensor's registration leaves (7-Scenes: one third within 4 px, the other up to
        // 16), not named.
        return None;
    };
    Some(format!(
        "the depth's outlines lie off the colour image's edges by ({}, {}) px on the left of the frame and ({}, {}) px on the right (medians over {} frames; registered depth lies within a few px): the depth looks not registered to the colour image but {how}; give the depth camera's --depth-intrinsics and --depth-to-colour so that pntr registers it, or record depth aligned to colour (where they are given, check them and the colour camera's --intrinsics: a wrong focal length stretches the registered depth alike)",
        left[0],
        left[1],
        right[0],
        right[1],
        measured
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame of boxes in front of a wall, each box a flat colour on a textured wall, and its depth
    /// moved by `shift` px and stretched about the centre by `scale`.
    fn boxes(w: u32, h: u32, shift: [i32; 2], scale: f64) -> (RgbImage, DepthMap) {
        let rects = [
            (60, 60, 180, 200),
            (260, 120, 380, 330),
            (450, 50, 590, 260),
            (100, 280, 220, 430),
            (420, 320, 600, 450),
        ];
        let inside = |x: f64, y: f64| {
            rects.iter().any(|&(x0, y0, x1, y1)| {
                x >= x0 as f64 && x < x1 as f64 && y >= y0 as f64 && y < y1 as f64
            })
        };
        let mut rgb = RgbImage {
            width: w,
            height: h,
            data: Vec::with_capacity((w * h * 3) as usize),
        };
        let mut depth = DepthMap {
            width: w,
            height: h,
            data: Vec::with_capacity((w * h) as usize),
        };
        let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
        for y in 0..h {
            for x in 0..w {
                let (xf, yf) = (x as f64, y as f64);
                let v = if inside(xf, yf) {
                    40
                } else {
                    150 + ((x * 7 + y * 3) % 11) as u8
                };
                rgb.data.extend([v, v, v]);
                // Depth pixel (x, y) sees what the colour pixel at its inverse map sees.
                let (u, t) = (
                    (xf - shift[0] as f64 - cx) / scale + cx,
                    (yf - shift[1] as f64 - cy) / scale + cy,
                );
                depth.data.push(if inside(u, t) { 1.2 } else { 3.0 });
            }
        }
        (rgb, depth)
    }

    #[test]
    fn registered_depth_meets_the_colour_edges() {
        let (rgb, depth) = boxes(640, 480, [0, 0], 1.0);
        let a = measure(&rgb, &depth);
        let within = |o: Option<[i32; 2]>| o.is_some_and(|o| o[0].abs() <= 1 && o[1].abs() <= 1);
        assert!(within(a.left) && within(a.right), "{a:?}");
        assert_eq!(misregistration_hint(&[a, a, a]), None);
    }

    #[test]
    fn a_few_pixels_off_is_within_a_real_sensors_registration() {
        let (rgb, depth) = boxes(640, 480, [-5, 3], 1.0);
        let a = measure(&rgb, &depth);
        assert_eq!(a.left, Some([5, -3]), "{a:?}");
        assert_eq!(misregistration_hint(&[a, a, a]), None);
    }

    #[test]
    fn a_shifted_depth_is_named() {
        let (rgb, depth) = boxes(640, 480, [-14, 3], 1.0);
        let a = measure(&rgb, &depth);
        // Depth outline + offset = colour edge: the offset undoes the shift.
        assert_eq!(a.left, Some([14, -3]), "{a:?}");
        assert_eq!(a.right, Some([14, -3]), "{a:?}");
        let hint = misregistration_hint(&[a, a, a]).expect("named");
        assert!(
            hint.contains("shifted") && hint.contains("--depth-to-colour"),
            "{hint}"
        );
    }

    #[test]
    fn a_stretched_depth_is_named() {
        // 7-Scenes: the depth camera's 585 px focal length against the colour camera's 525.
        let (rgb, depth) = boxes(640, 480, [0, 0], 585.0 / 525.0);
        let a = measure(&rgb, &depth);
        let (l, r) = (a.left.expect("left"), a.right.expect("right"));
        assert!(l[0] > 8 && r[0] < -8, "{a:?}");
        let hint = misregistration_hint(&[a, a, a]).expect("named");
        assert!(
            hint.contains("stretched") && hint.contains("--depth-intrinsics"),
            "{hint}"
        );
    }

    #[test]
    fn thirds_off_without_a_lens_or_offset_pattern_are_not_named() {
        // 7-Scenes' Kinect depth registered with its translation offset: the left third within
        // 4 px, the right one 16 px off, in frames 350-499.
        let real = Alignment {
            left: Some([0, -4]),
            right: Some([-16, -11]),
            width: 640,
        };
        assert_eq!(misregistration_hint(&[real, real, real]), None);
    }

    #[test]
    fn too_few_frames_or_outlines_say_nothing() {
        let (rgb, depth) = boxes(640, 480, [-14, 3], 1.0);
        let a = measure(&rgb, &depth);
        assert_eq!(misregistration_hint(&[a, a]), None);
        let flat = DepthMap {
            width: 640,
            height: 480,
            data: vec![2.0; 640 * 480],
        };
        let none = measure(&rgb, &flat);
        assert_eq!((none.left, none.right), (None, None));
        assert_eq!(misregistration_hint(&[none, none, none]), None);
    }
}
