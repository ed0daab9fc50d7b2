//! Wire frames to pipeline queries: decode, check, and refuse with a message a client can act on.
//!
//! Every check that does not need the map runs here, on the async side, before a request takes a
//! place in the queue: a malformed frame costs microseconds and never occupies a worker. Sizes are
//! checked against the configured limits *before* anything is allocated or decoded (PNG and JPEG
//! headers are read first), so a hostile header cannot make the server allocate gigabytes.
//!
//! Missing depth is data, not an error: 0, negative, NaN and infinite pixels (ROS sends NaN,
//! RealSense 0) become 0, the pipeline's "no depth here"; only a frame with no valid pixel at all is
//! refused.
//!
//! Integration mistakes get an error that names them: depth in the wrong unit (a median valid depth
//! outside [`MIN_MEDIAN_DEPTH_M`] .. [`MAX_MEDIAN_DEPTH_M`]), a principal point outside the image (with
//! a hint when swapping the axes would fit: a rotated image sent with the unrotated camera), and a
//! depth image that does not match the colour image after its JPEG EXIF orientation is applied.

use std::io::Cursor;

use image::metadata::Orientation;

use nalgebra::Vector3;
use pntr_core::{DepthMap, Intrinsics, RgbImage};
use pntr_pipeline::pipeline::Query;
use pntr_pipeline::prior::Region;
use pntr_pipeline::PipelineError;
use tonic::Status;

use crate::proto;

/// Size limits applied to every frame.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Largest width.
    pub max_width: u32,
    /// Largest height.
    pub max_height: u32,
}

/// Smallest plausible median of a frame's valid depths, metres: below it the values are in a larger
/// unit than declared (metres stored in a millimetre image).
pub const MIN_MEDIAN_DEPTH_M: f32 = 0.05;
/// Largest plausible median of a frame's valid depths, metres: above it the values are in a smaller
/// unit than declared (millimetres sent as FLOAT32_METERS).
pub const MAX_MEDIAN_DEPTH_M: f32 = 50.0;

fn invalid<T>(m: impl Into<String>) -> Result<T, Status> {
    Err(Status::invalid_argument(m.into()))
}

impl Limits {
    fn check(&self, what: &str, w: u32, h: u32) -> Result<(), Status> {
        if w == 0 || h == 0 {
            return invalid(format!("{what} is {w}x{h}: width and height must be set"));
        }
        if w > self.max_width || h > self.max_height {
            return invalid(format!(
                "{what} is {w}x{h}, larger than this server's limit of {}x{}",
                self.max_width, self.max_height
            ));
        }
        Ok(())
    }
}

/// The convention a request asks for: its own, or the server's `default` when it leaves it unset;
/// INVALID_ARGUMENT for a value this server does not know.
pub fn frame_convention(
    requested: i32,
    default: proto::FrameConvention,
) -> Result<proto::FrameConvention, Status> {
    match proto::FrameConvention::try_from(requested) {
        Ok(proto::FrameConvention::Unspecified) => Ok(default),
        Ok(c) => Ok(c),
        Err(_) => invalid(format!(
            "frame_convention {requested} is not FRAME_CONVENTION_MAP (1) or FRAME_CONVENTION_ROS (2)"
        )),
    }
}

/// Stamps at or above this many seconds are taken for another unit: 1e11 s is the year 5138, and
/// Unix time in milliseconds (about 1.8e12 in 2026) or nanoseconds lies above it.
pub const MAX_STAMP_S: f64 = 1e11;

/// A request's capture stamp (`LocalizeRequest.stamp_s`, seconds; `None`: not given), or what is
/// wrong with it: INVALID_ARGUMENT for a negative or non-finite value and for one of
/// [`MAX_STAMP_S`] and more, named as milliseconds, microseconds or nanoseconds.
pub fn stamp(stamp_s: Option<f64>) -> Result<Option<f64>, Status> {
    let Some(stamp_s) = stamp_s else {
        return Ok(None);
    };
    if !stamp_s.is_finite() || stamp_s < 0.0 {
        return invalid(format!(
            "stamp_s = {stamp_s}: the frame's capture time must be a finite number of seconds >= 0"
        ));
    }
    if stamp_s >= MAX_STAMP_S {
        let unit = if stamp_s >= 1e17 {
            "nanoseconds"
        } else if stamp_s >= 1e14 {
            "microseconds"
        } else {
            "milliseconds"
        };
        return invalid(format!(
            "stamp_s = {stamp_s}: this looks like {unit}; give seconds (a ROS header.stamp is sec + nanosec * 1e-9)"
        ));
    }
    Ok(Some(stamp_s))
}

/// The search region of a request's prior (`None` without one), or what is wrong with it.
pub fn prior(req: &proto::LocalizeRequest) -> Result<Option<Region>, Status> {
    let Some(prior) = &req.prior else {
        return Ok(None);
    };
    let Some(t) = prior.pose.as_ref().and_then(|p| p.translation.as_ref()) else {
        return invalid("prior: pose.translation is missing (the position, map frame, metres)");
    };
    let center = Vector3::new(t.x, t.y, t.z);
    let region = if prior.radius_m != 0.0 || prior.covariance.is_empty() {
        if prior.radius_m == 0.0 {
            return invalid(
                "prior: give radius_m > 0 or a 36-value covariance (the region to search)",
            );
        }
        Region::new(center, prior.radius_m)
    } else {
        Region::from_covariance(center, &prior.covariance)
    };
    region.map(Some).map_err(status_of)
}

/// A pose a stream's frame carries besides the image (`LocalizeRequest.odometry`,
/// `TrackContinuation.pose`): `None` when absent; INVALID_ARGUMENT naming `field` when its
/// translation or rotation is missing or non-finite, or the rotation is not a unit quaternion
/// (within 1e-3).
pub fn stream_pose(
    field: &str,
    p: Option<&proto::Pose>,
) -> Result<Option<nalgebra::Isometry3<f64>>, Status> {
    let Some(p) = p else {
        return Ok(None);
    };
    let (Some(t), Some(q)) = (p.translation.as_ref(), p.rotation.as_ref()) else {
        return invalid(format!(
            "{field}: give both translation (metres) and rotation (a unit quaternion)"
        ));
    };
    let values = [t.x, t.y, t.z, q.x, q.y, q.z, q.w];
    let norm = (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w).sqrt();
    if values.iter().any(|v| !v.is_finite()) {
        return invalid(format!(
            "{field}: the translation and rotation must be finite"
        ));
    }
    // A unit quaternion, as ROS messages carry it (a little rounding allowed): another length is
    // a mistake (a rotation vector, Euler angles or a matrix row put in its place).
    if (norm - 1.0).abs() > 1e-3 {
        return invalid(format!(
            "{field}: the rotation must be a unit quaternion (x, y, z, w), its length is {norm:.4}"
        ));
    }
    Ok(crate::wire::pose(Some(p)))
}

/// The gRPC status of a pipeline error: the one mapping, exhaustive so that a new kind of error must
/// choose its code. A query the pipeline cannot use is the caller's (INVALID_ARGUMENT); everything
/// else is the server's (INTERNAL, the message logged by the caller).
pub fn status_of(e: PipelineError) -> Status {
    match e {
        PipelineError::Query(m) => Status::invalid_argument(m),
        PipelineError::Refused(m) => Status::failed_precondition(m),
        e @ (PipelineError::Config(_)
        | PipelineError::MapFile { .. }
        | PipelineError::Io { .. }
        | PipelineError::Dataset(_)
        | PipelineError::Features(_)
        | PipelineError::Retrieval(_)) => Status::internal(format!("localization failed: {e}")),
    }
}

/// Turn a request into a pipeline query, or say precisely what is wrong with it.
pub fn query(req: &proto::LocalizeRequest, limits: &Limits) -> Result<Query, Status> {
    stamp(req.stamp_s)?;
    let Some(rgb) = &req.rgb else {
        return invalid("rgb is missing");
    };
    let Some(depth) = &req.depth else {
        return invalid("depth is missing");
    };
    let (rgb, orientation) = decode_rgb(rgb, limits)?;
    let depth_encoding = depth.encoding;
    let depth = decode_depth(depth, limits)?;
    if (rgb.width, rgb.height) != (depth.width, depth.height) {
        if let Some((o, (w, h))) = orientation {
            return invalid(format!(
                "rgb is {w}x{h} as encoded and {}x{} after its EXIF orientation {} ({o:?}), but depth is {}x{}: depth must match the upright image",
                rgb.width,
                rgb.height,
                o.to_exif(),
                depth.width,
                depth.height
            ));
        }
        return invalid(format!(
            "rgb is {}x{} but depth is {}x{}: they must be the same size, pixel-aligned",
            rgb.width, rgb.height, depth.width, depth.height
        ));
    }
    let intrinsics = intrinsics(req.intrinsics.as_ref(), rgb.width, rgb.height)?;
    check_depth_unit(&depth, depth_encoding)?;
    Ok(Query {
        rgb,
        depth,
        intrinsics,
    })
}

/// Refuse a depth image whose values are implausible for its declared unit, naming the unit they look
/// like; also refuse one without a valid pixel.
fn check_depth_unit(depth: &DepthMap, encoding: i32) -> Result<(), Status> {
    // A strided sample of at most ~8k valid pixels is plenty for a median whose plausible range
    // spans two orders of magnitude.
    let stride = (depth.data.len() / 8_192).max(1);
    let mut valid: Vec<f32> = depth
        .data
        .iter()
        .step_by(stride)
        .copied()
        .filter(|&d| d > 0.0)
        .collect();
    if valid.is_empty() && !depth.data.iter().any(|&d| d > 0.0) {
        return invalid("depth has no valid pixel (every value is 0, negative, NaN or infinite)");
    }
    if valid.is_empty() {
        return Ok(());
    }
    let mid = valid.len() / 2;
    let (_, &mut median, _) = valid.select_nth_unstable_by(mid, f32::total_cmp);
    let meters = encoding == proto::DepthEncoding::Float32Meters as i32;
    let declared = proto::DepthEncoding::try_from(encoding)
        .map(|e| e.as_str_name())
        .unwrap_or("the declared encoding");
    if median > MAX_MEDIAN_DEPTH_M {
        let hint = if meters {
            "these look like millimetres: send UINT16_MILLIMETERS, or divide by 1000"
        } else {
            "these look like a unit finer than millimetres (e.g. 0.1 mm): convert to millimetres"
        };
        return invalid(format!(
            "depth ({declared}) has a median valid depth of {median:.1} m, beyond the plausible {MAX_MEDIAN_DEPTH_M} m: {hint}"
        ));
    }
    if median < MIN_MEDIAN_DEPTH_M {
        let hint = if meters {
            "these look like a unit larger than metres, or normalised or inverse depth: send metres"
        } else {
            "these look like metres stored in a millimetre image: multiply by 1000, or send FLOAT32_METERS"
        };
        return invalid(format!(
            "depth ({declared}) has a median valid depth of {median:.4} m, below the plausible {MIN_MEDIAN_DEPTH_M} m: {hint}"
        ));
    }
    Ok(())
}

/// The camera of a request: its intrinsics message (or the HPointLoc camera for 256x256 frames when absent),
/// checked, for a frame of `w` x `h` pixels.
pub fn intrinsics(k: Option<&proto::Intrinsics>, w: u32, h: u32) -> Result<Intrinsics, Status> {
    let Some(k) = k else {
        if (w, h) == (256, 256) {
            return Ok(Intrinsics::hpointloc());
        }
        return invalid(format!(
            "intrinsics required: they default to the HPointLoc camera only for 256x256 frames, this one is {w}x{h}"
        ));
    };
    if !(k.fx.is_finite() && k.fy.is_finite() && k.fx > 0.0 && k.fy > 0.0) {
        return invalid(format!(
            "intrinsics fx = {} and fy = {}: focal lengths must be positive and finite",
            k.fx, k.fy
        ));
    }
    if k.fx < 1.0 || k.fy < 1.0 || k.fx > 1e6 || k.fy > 1e6 {
        return invalid(format!(
            "intrinsics fx = {} and fy = {}: focal lengths are in pixels, 1 to 1e6 (normalised or metric intrinsics? multiply by the image size)",
            k.fx, k.fy
        ));
    }
    if !(k.cx.is_finite() && k.cy.is_finite()) {
        return invalid(format!(
            "intrinsics cx = {} and cy = {}: the principal point must be finite",
            k.cx, k.cy
        ));
    }
    let mut distortion = [0.0; 5];
    match k.distortion.len() {
        0 => {}
        4 | 5 => distortion[..k.distortion.len()].copy_from_slice(&k.distortion),
        n => {
            return invalid(format!(
                "intrinsics.distortion has {n} values: give [k1, k2, p1, p2, k3] (plumb_bob, ROS CameraInfo.d), [k1, k2, p1, p2], or none"
            ))
        }
    }
    let out = Intrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        width: w,
        height: h,
        distortion,
    };
    if let Err(e) = out.validate() {
        // A rotated image sent with the camera of the unrotated one: the swapped axes would fit.
        let swapped = Intrinsics {
            cx: k.cy,
            cy: k.cx,
            ..out
        };
        let hint = if out.cx != out.cy && swapped.validate().is_ok() {
            " (cx and cy would fit the image with its axes swapped: was the image rotated without rotating the intrinsics?)"
        } else {
            ""
        };
        return invalid(format!("intrinsics: {}{hint}", e.0));
    }
    // Frames and cameras no RGB-D sensor makes, refused before they cost a resampling: a strip of
    // pixels, pixels far from square (fx and fy of different cameras, or a typo), a field of view a
    // pinhole camera cannot have (focal length in another unit).
    if w.min(h) < 16 || w.max(h) > 8 * w.min(h) {
        return invalid(format!(
            "a {w}x{h} frame is not a camera image pntr can use: each side needs at least 16 pixels and the aspect ratio at most 8:1"
        ));
    }
    let ratio = k.fx / k.fy;
    if !(1.0 / 3.0..=3.0).contains(&ratio) {
        return invalid(format!(
            "intrinsics fx = {} and fy = {} differ by a factor of {:.3}: camera pixels are close to square (are they swapped with cx, cy, or from two cameras?)",
            k.fx, k.fy, ratio.max(1.0 / ratio)
        ));
    }
    let fov = |side: u32, f: f64| 2.0 * (side as f64 / (2.0 * f)).atan().to_degrees();
    let (hfov, vfov) = (fov(w, k.fx), fov(h, k.fy));
    if hfov.max(vfov) > 170.0 || hfov.min(vfov) < 1.0 {
        return invalid(format!(
            "intrinsics fx = {} and fy = {} give a {hfov:.1} x {vfov:.1} degree field of view for a {w}x{h} frame: a pinhole camera sees 1 to 170 degrees (focal lengths are in pixels of this frame: scaled with the image?)",
            k.fx, k.fy
        ));
    }
    // A quarter-turned image sent with the camera of the upright one: the principal point sits at
    // the centre of the image with its axes swapped and far from this one's centre.
    let (wf, hf) = (w as f64 - 1.0, h as f64 - 1.0);
    let off = (k.cx - wf / 2.0).abs() + (k.cy - hf / 2.0).abs();
    let swapped_off = (k.cx - hf / 2.0).abs() + (k.cy - wf / 2.0).abs();
    let side = w.max(h) as f64;
    if w != h && swapped_off < 0.02 * side && off > 0.1 * side {
        return invalid(format!(
            "intrinsics: principal point ({}, {}) is the centre of a {h}x{w} image but this one is {w}x{h}: was the image rotated without rotating the intrinsics (swap fx with fy and cx with cy)?",
            k.cx, k.cy
        ));
    }
    Ok(out)
}

/// Expected byte count of a raw `w` x `h` image with `bpp` bytes per pixel, checked against `len`.
fn raw_len(what: &str, w: u32, h: u32, bpp: u64, len: usize, unit: &str) -> Result<(), Status> {
    let want = w as u64 * h as u64 * bpp;
    if want != len as u64 {
        return invalid(format!(
            "{what} is {w}x{h} {unit} ({want} bytes) but its data has {len} bytes"
        ));
    }
    Ok(())
}

/// Declared size must agree with the decoded one, where the client declared it.
fn declared(what: &str, (dw, dh): (u32, u32), (w, h): (u32, u32)) -> Result<(), Status> {
    if (dw, dh) != (0, 0) && (dw, dh) != (w, h) {
        return invalid(format!(
            "{what} declares {dw}x{dh} but the encoded image is {w}x{h}"
        ));
    }
    Ok(())
}

/// The colour image, upright; with the EXIF orientation applied and the encoded size, when a JPEG
/// had one other than "no transform".
type Oriented = (RgbImage, Option<(Orientation, (u32, u32))>);

fn decode_rgb(im: &proto::Image, limits: &Limits) -> Result<Oriented, Status> {
    use proto::ImageEncoding as E;
    let mut orientation = None;
    let (w, h, data) = match E::try_from(im.encoding) {
        Ok(E::RawRgb8) => {
            limits.check("rgb", im.width, im.height)?;
            raw_len("rgb", im.width, im.height, 3, im.data.len(), "RAW_RGB8")?;
            (im.width, im.height, im.data.clone())
        }
        Ok(E::Png) => {
            let (w, h, data) = decode_png_rgb(&im.data, limits)?;
            declared("rgb", (im.width, im.height), (w, h))?;
            (w, h, data)
        }
        Ok(E::Jpeg) => {
            let (w, h, data, o) = decode_jpeg(&im.data, limits)?;
            declared("rgb", (im.width, im.height), (w, h))?;
            if o != Orientation::NoTransforms {
                let buf = image::RgbImage::from_raw(w, h, data).ok_or_else(|| {
                    Status::invalid_argument("rgb: JPEG decoded to the wrong size")
                })?;
                let mut img = image::DynamicImage::ImageRgb8(buf);
                img.apply_orientation(o);
                let img = img.into_rgb8();
                orientation = Some((o, (w, h)));
                let (ow, oh) = img.dimensions();
                limits.check("rgb (after its EXIF orientation)", ow, oh)?;
                return RgbImage::new(ow, oh, img.into_raw())
                    .map(|r| (r, orientation))
                    .or_else(|e| invalid(format!("rgb: {e}")));
            }
            (w, h, data)
        }
        Ok(E::Unspecified) => {
            return invalid("rgb.encoding is IMAGE_ENCODING_UNSPECIFIED: set RAW_RGB8, PNG or JPEG")
        }
        Err(_) => {
            return invalid(format!(
                "rgb.encoding {} is not a known ImageEncoding",
                im.encoding
            ))
        }
    };
    RgbImage::new(w, h, data)
        .map(|r| (r, orientation))
        .or_else(|e| invalid(format!("rgb: {e}")))
}

fn sanitize(d: f32) -> f32 {
    if d.is_finite() && d > 0.0 {
        d
    } else {
        0.0
    }
}

fn decode_depth(d: &proto::Depth, limits: &Limits) -> Result<DepthMap, Status> {
    use proto::DepthEncoding as E;
    let (w, h, data) = match E::try_from(d.encoding) {
        Ok(E::Float32Meters) => {
            limits.check("depth", d.width, d.height)?;
            raw_len("depth", d.width, d.height, 4, d.data.len(), "FLOAT32_METERS")?;
            let v = d
                .data
                .chunks_exact(4)
                .map(|b| sanitize(f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
                .collect();
            (d.width, d.height, v)
        }
        Ok(E::Uint16Millimeters) => {
            limits.check("depth", d.width, d.height)?;
            raw_len("depth", d.width, d.height, 2, d.data.len(), "UINT16_MILLIMETERS")?;
            let v = d
                .data
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]) as f32 / 1000.0)
                .collect();
            (d.width, d.height, v)
        }
        Ok(E::Png16Millimeters) => {
            let (w, h, v) = decode_png16(&d.data, limits)?;
            declared("depth", (d.width, d.height), (w, h))?;
            (w, h, v)
        }
        Ok(E::Unspecified) => {
            return invalid(
                "depth.encoding is DEPTH_ENCODING_UNSPECIFIED: set FLOAT32_METERS, UINT16_MILLIMETERS or PNG16_MILLIMETERS",
            )
        }
        Err(_) => return invalid(format!("depth.encoding {} is not a known DepthEncoding", d.encoding)),
    };
    // `from_metres` would refuse nothing here (values are already sanitised); sizes are checked above.
    DepthMap::from_metres(w, h, data).or_else(|e| invalid(format!("depth: {e}")))
}

/// Read a PNG's header and check its size before decoding the pixels.
fn png_reader<'a>(
    what: &str,
    data: &'a [u8],
    limits: &Limits,
) -> Result<png::Reader<Cursor<&'a [u8]>>, Status> {
    // The decoder's allocation cap follows the size limit (RGBA, 16 bits per sample, plus slack).
    let bytes = limits.max_width as usize * limits.max_height as usize * 8 + (1 << 20);
    let mut dec = png::Decoder::new_with_limits(Cursor::new(data), png::Limits { bytes });
    // Expand palettes and low bit depths to 8 bits; 16-bit samples stay 16-bit.
    dec.set_transformations(png::Transformations::EXPAND);
    let reader = dec
        .read_info()
        .or_else(|e| invalid(format!("{what}: not a readable PNG ({e})")))?;
    let (w, h) = (reader.info().width, reader.info().height);
    limits.check(what, w, h)?;
    Ok(reader)
}

fn png_pixels(what: &str, reader: &mut png::Reader<Cursor<&[u8]>>) -> Result<Vec<u8>, Status> {
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| Status::invalid_argument(format!("{what}: PNG too large")))?;
    let mut buf = vec![0u8; size];
    let info = reader
        .next_frame(&mut buf)
        .or_else(|e| invalid(format!("{what}: PNG data cannot be decoded ({e})")))?;
    buf.truncate(info.buffer_size());
    Ok(buf)
}

/// Decode an 8-bit PNG (RGB, RGBA, grey) to RGB8: (width, height, pixels).
pub fn decode_png_rgb(data: &[u8], limits: &Limits) -> Result<(u32, u32, Vec<u8>), Status> {
    let mut reader = png_reader("rgb", data, limits)?;
    let (w, h) = (reader.info().width, reader.info().height);
    let buf = png_pixels("rgb", &mut reader)?;
    let (color, depth) = reader.output_color_type();
    let channels = color.samples();
    let bytes = if depth == png::BitDepth::Sixteen {
        2
    } else {
        1
    };
    let n = w as usize * h as usize;
    if buf.len() != n * channels * bytes {
        return invalid(format!(
            "rgb: PNG decoded to {} bytes, expected {}",
            buf.len(),
            n * channels * bytes
        ));
    }
    let mut out = Vec::with_capacity(n * 3);
    // 16-bit samples are big-endian in PNG: the high byte is the 8-bit value.
    let sample = |px: &[u8], c: usize| px[c * bytes];
    for px in buf.chunks_exact(channels * bytes) {
        match color {
            png::ColorType::Grayscale | png::ColorType::GrayscaleAlpha => {
                let g = sample(px, 0);
                out.extend_from_slice(&[g, g, g]);
            }
            png::ColorType::Rgb | png::ColorType::Rgba => {
                out.extend_from_slice(&[sample(px, 0), sample(px, 1), sample(px, 2)]);
            }
            png::ColorType::Indexed => {
                return invalid("rgb: PNG palette was not expanded");
            }
        }
    }
    Ok((w, h, out))
}

/// Decode a 16-bit grey PNG of millimetres to metres (0 = missing): (width, height, depths).
pub fn decode_png16(data: &[u8], limits: &Limits) -> Result<(u32, u32, Vec<f32>), Status> {
    let mut reader = png_reader("depth", data, limits)?;
    let (w, h) = (reader.info().width, reader.info().height);
    let (color, depth) = (reader.info().color_type, reader.info().bit_depth);
    if color != png::ColorType::Grayscale || depth != png::BitDepth::Sixteen {
        return invalid(format!(
            "depth: PNG16_MILLIMETERS needs a 16-bit greyscale PNG, this one is {color:?} {depth:?}"
        ));
    }
    let buf = png_pixels("depth", &mut reader)?;
    if buf.len() != w as usize * h as usize * 2 {
        return invalid("depth: PNG decoded to an unexpected size");
    }
    let v = buf
        .chunks_exact(2)
        .map(|b| u16::from_be_bytes([b[0], b[1]]) as f32 / 1000.0)
        .collect();
    Ok((w, h, v))
}

/// The size of a `w` x `h` image once `o` is applied (the quarter turns swap the axes).
pub fn upright_size(w: u32, h: u32, o: Orientation) -> (u32, u32) {
    use Orientation as O;
    match o {
        O::Rotate90 | O::Rotate270 | O::Rotate90FlipH | O::Rotate270FlipH => (h, w),
        O::NoTransforms | O::Rotate180 | O::FlipHorizontal | O::FlipVertical => (w, h),
    }
}

/// Decode a JPEG to RGB8: (width, height, pixels as encoded, EXIF orientation). The orientation is
/// read with the `image` crate's EXIF parser (`NoTransforms` without EXIF or with an invalid tag).
pub fn decode_jpeg(
    data: &[u8],
    limits: &Limits,
) -> Result<(u32, u32, Vec<u8>, Orientation), Status> {
    use zune_jpeg::zune_core::bytestream::ZCursor;
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let opts = DecoderOptions::default()
        .jpeg_set_out_colorspace(ColorSpace::RGB)
        .set_max_width(limits.max_width as usize)
        .set_max_height(limits.max_height as usize);
    let mut dec = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(data), opts);
    dec.decode_headers()
        .or_else(|e| invalid(format!("rgb: not a readable JPEG ({e:?})")))?;
    let (w, h) = dec
        .dimensions()
        .ok_or_else(|| Status::invalid_argument("rgb: JPEG without dimensions"))?;
    limits.check("rgb", w as u32, h as u32)?;
    let px = dec
        .decode()
        .or_else(|e| invalid(format!("rgb: JPEG data cannot be decoded ({e:?})")))?;
    let orientation = dec
        .exif()
        .and_then(|x| Orientation::from_exif_chunk(x))
        .unwrap_or(Orientation::NoTransforms);
    let n = w * h;
    let rgb = match dec.output_colorspace() {
        Some(ColorSpace::RGB) if px.len() == n * 3 => px,
        Some(ColorSpace::Luma) if px.len() == n => px.iter().flat_map(|&g| [g, g, g]).collect(),
        other => {
            return invalid(format!(
                "rgb: JPEG decoded to {other:?} with {} bytes, expected RGB",
                px.len()
            ))
        }
    };
    Ok((w as u32, h as u32, rgb, orientation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire;

    const LIMITS: Limits = Limits {
        max_width: 4096,
        max_height: 4096,
    };

    fn frame(w: u32, h: u32) -> (RgbImage, DepthMap) {
        let rgb =
            RgbImage::new(w, h, (0..w * h * 3).map(|i| (i * 7 % 251) as u8).collect()).unwrap();
        let depth = DepthMap::from_metres(
            w,
            h,
            (0..w * h).map(|i| 0.5 + (i % 100) as f32 * 0.01).collect(),
        )
        .unwrap();
        (rgb, depth)
    }

    fn code_msg(r: Result<Query, Status>) -> (tonic::Code, String) {
        let e = r.unwrap_err();
        (e.code(), e.message().to_string())
    }

    #[test]
    fn raw_and_png_round_trip() {
        let (rgb, depth) = frame(256, 256);
        let raw = wire::raw_request(&rgb, &depth, None);
        let q = query(&raw, &LIMITS).unwrap();
        assert_eq!(q.rgb, rgb);
        assert_eq!(q.intrinsics, Intrinsics::hpointloc());
        let png = wire::png_request(&rgb, &depth, None).unwrap();
        let p = query(&png, &LIMITS).unwrap();
        assert_eq!(p.rgb, rgb);
        for (a, b) in p.depth.data.iter().zip(&depth.data) {
            assert!((a - b).abs() <= 0.0005 + 1e-6, "{a} {b}");
        }
        let mut u16req = raw.clone();
        u16req.depth = Some(proto::Depth {
            width: 256,
            height: 256,
            encoding: proto::DepthEncoding::Uint16Millimeters as i32,
            data: depth
                .data
                .iter()
                .flat_map(|d| ((d * 1000.0).round() as u16).to_le_bytes())
                .collect(),
        });
        let u = query(&u16req, &LIMITS).unwrap();
        assert!((u.depth.data[5] - depth.data[5]).abs() < 0.001);
    }

    #[test]
    fn bad_frames_are_refused_with_reasons() {
        let (rgb, depth) = frame(256, 256);
        let good = wire::raw_request(&rgb, &depth, None);

        let mut r = good.clone();
        r.rgb = None;
        assert_eq!(code_msg(query(&r, &LIMITS)).1, "rgb is missing");
        let mut r = good.clone();
        r.depth = None;
        assert_eq!(code_msg(query(&r, &LIMITS)).1, "depth is missing");

        let mut r = good.clone();
        r.rgb.as_mut().unwrap().width = 255;
        let (c, m) = code_msg(query(&r, &LIMITS));
        assert_eq!(c, tonic::Code::InvalidArgument);
        assert!(m.contains("255x256") && m.contains("196608"), "{m}");

        let (small_rgb, _) = frame(128, 256);
        let mut r = good.clone();
        r.rgb = wire::raw_request(&small_rgb, &depth, None).rgb;
        let m = code_msg(query(&r, &LIMITS)).1;
        assert!(m.contains("same size"), "{m}");

        let mut r = good.clone();
        r.rgb.as_mut().unwrap().encoding = proto::ImageEncoding::Png as i32;
        let m = code_msg(query(&r, &LIMITS)).1;
        assert!(m.contains("not a readable PNG"), "{m}");
        let mut r = good.clone();
        r.rgb.as_mut().unwrap().encoding = proto::ImageEncoding::Jpeg as i32;
        let m = code_msg(query(&r, &LIMITS)).1;
        assert!(m.contains("not a readable JPEG"), "{m}");
        let mut r = good.clone();
        r.rgb.as_mut().unwrap().encoding = 0;
        let m = code_msg(query(&r, &LIMITS)).1;
        assert!(m.contains("UNSPECIFIED"), "{m}");
        let mut r = good.clone();
        r.depth.as_mut().unwrap().encoding = 17;
        let m = code_msg(query(&r, &LIMITS)).1;
        assert!(m.contains("17"), "{m}");

        for (fx, fy) in [
            (0.0, 128.0),
            (-1.0, 128.0),
            (128.0, f64::NAN),
            (f64::INFINITY, 1.0),
            (0.9, 0.9),
        ] {
            let mut r = good.clone();
            r.intrinsics = Some(proto::Intrinsics {
                fx,
                fy,
                cx: 127.5,
                cy: 127.5,
                distortion: Vec::new(),
            });
            let m = code_msg(query(&r, &LIMITS)).1;
            assert!(m.contains("focal"), "{m}");
        }

        let (r2, d2) = frame(64, 48);
        let m = code_msg(query(&wire::raw_request(&r2, &d2, None), &LIMITS)).1;
        assert!(m.contains("intrinsics required"), "{m}");

        let tiny = Limits {
            max_width: 100,
            max_height: 100,
        };
        let m = code_msg(query(&good, &tiny)).1;
        assert!(m.contains("limit"), "{m}");
        let png = wire::png_request(&rgb, &depth, None).unwrap();
        let m = code_msg(query(&png, &tiny)).1;
        assert!(m.contains("limit"), "{m}");

        // Missing depth in every form is skipped...
        let mut bad = depth.clone();
        bad.data[0] = f32::NAN;
        bad.data[1] = f32::INFINITY;
        bad.data[2] = -1.0;
        bad.data[3] = 0.0;
        let mut r = wire::raw_request(&rgb, &depth, None);
        r.depth.as_mut().unwrap().data = bad.data.iter().flat_map(|d| d.to_le_bytes()).collect();
        let q = query(&r, &LIMITS).unwrap();
        assert_eq!(&q.depth.data[..4], &[0.0; 4]);
        assert_eq!(q.depth.data[4], depth.data[4]);
        // ...but a frame with none at all is refused.
        r.depth.as_mut().unwrap().data = [f32::NAN, 0.0, -2.0]
            .iter()
            .cycle()
            .take(256 * 256)
            .flat_map(|d| d.to_le_bytes())
            .collect();
        let m = code_msg(query(&r, &LIMITS)).1;
        assert!(m.contains("no valid pixel"), "{m}");
    }
}
