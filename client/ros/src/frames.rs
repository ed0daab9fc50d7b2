//! ROS 2 camera messages as pntr requests: colour (`sensor_msgs/Image` rgb8, bgr8, rgba8, bgra8,
//! mono8, or a `CompressedImage` JPEG/PNG passed through undecoded), depth (`16UC1`/`mono16`
//! millimetres, `32FC1` metres, or image_transport's `compressedDepth`), and the intrinsics of a
//! `CameraInfo`. Every refusal names the topic's likely mistake.

use crate::msgs;
use crate::proto;

/// A colour or depth message as received.
#[derive(Clone, Debug)]
pub enum Received {
    /// sensor_msgs/Image.
    Raw(msgs::Image),
    /// sensor_msgs/CompressedImage.
    Compressed(msgs::CompressedImage),
}

impl Received {
    /// The message's header.
    pub fn header(&self) -> &msgs::Header {
        match self {
            Received::Raw(m) => &m.header,
            Received::Compressed(m) => &m.header,
        }
    }
}

/// Rows of `bytes_per_pixel * width` bytes taken from an image whose rows are `step` bytes apart.
fn packed_rows(m: &msgs::Image, bytes_per_pixel: usize) -> Result<Vec<u8>, String> {
    let (w, h, step) = (m.width as usize, m.height as usize, m.step as usize);
    let row = w * bytes_per_pixel;
    if w == 0 || h == 0 {
        return Err(format!("{}: the image is {w}x{h}", m.encoding));
    }
    if step < row || m.data.len() < step * (h - 1) + row {
        return Err(format!(
            "{} {w}x{h}: step {step} and {} bytes of data, but a row needs {row} bytes",
            m.encoding,
            m.data.len()
        ));
    }
    if step == row {
        return Ok(m.data[..row * h].to_vec());
    }
    Ok((0..h)
        .flat_map(|r| m.data[r * step..r * step + row].iter().copied())
        .collect())
}

/// The colour image of a request.
pub fn colour(m: &Received) -> Result<proto::Image, String> {
    match m {
        Received::Compressed(c) => {
            let encoding = if c.data.starts_with(&[0xFF, 0xD8]) {
                proto::ImageEncoding::Jpeg
            } else if c.data.starts_with(b"\x89PNG") {
                proto::ImageEncoding::Png
            } else {
                return Err(format!(
                    "colour: a CompressedImage of format {:?} that is neither JPEG nor PNG",
                    c.format
                ));
            };
            Ok(proto::Image {
                width: 0,
                height: 0,
                encoding: encoding as i32,
                data: c.data.clone(),
            })
        }
        Received::Raw(i) => {
            let (order, bpp): ([usize; 3], usize) = match i.encoding.as_str() {
                "rgb8" => ([0, 1, 2], 3),
                "bgr8" => ([2, 1, 0], 3),
                "rgba8" => ([0, 1, 2], 4),
                "bgra8" => ([2, 1, 0], 4),
                "mono8" | "8UC1" => ([0, 0, 0], 1),
                "16UC1" | "mono16" | "32FC1" => {
                    return Err(format!(
                        "colour: the image is {} (a depth encoding): rgb_topic names a depth topic",
                        i.encoding
                    ))
                }
                other => {
                    return Err(format!(
                        "colour: encoding {other:?} is not supported (rgb8, bgr8, rgba8, bgra8, mono8, or the /compressed topic)"
                    ))
                }
            };
            let packed = packed_rows(i, bpp)?;
            let data = if bpp == 3 && order == [0, 1, 2] {
                packed
            } else {
                packed
                    .chunks_exact(bpp)
                    .flat_map(|p| order.map(|c| p[c]))
                    .collect()
            };
            Ok(proto::Image {
                width: i.width,
                height: i.height,
                encoding: proto::ImageEncoding::RawRgb8 as i32,
                data,
            })
        }
    }
}

/// compressed_depth_image_transport's 12-byte ConfigHeader (int32 format, float32 depthParam[2]).
const DEPTH_HEADER: usize = 12;

/// The depth image of a request.
pub fn depth(m: &Received) -> Result<proto::Depth, String> {
    match m {
        Received::Compressed(c) => {
            let (encoding, kind) = c.format.split_once(';').unwrap_or(("", c.format.as_str()));
            let kind = kind.trim();
            if !kind.starts_with("compressedDepth") {
                return Err(format!(
                    "depth: a CompressedImage of format {:?}: depth must come as compressedDepth (a `compressed` depth image has lost its precision)",
                    c.format
                ));
            }
            if kind.ends_with("rvl") {
                return Err(
                    "depth: compressedDepth rvl is not supported: publish png (the `format` parameter of compressed_depth_image_transport)"
                        .into(),
                );
            }
            if c.data.len() <= DEPTH_HEADER || !c.data[DEPTH_HEADER..].starts_with(b"\x89PNG") {
                return Err(format!(
                    "depth: compressedDepth data of {} bytes without a PNG after its 12-byte header",
                    c.data.len()
                ));
            }
            let png = &c.data[DEPTH_HEADER..];
            match encoding.trim() {
                "16UC1" | "mono16" | "" => Ok(proto::Depth {
                    width: 0,
                    height: 0,
                    encoding: proto::DepthEncoding::Png16Millimeters as i32,
                    data: png.to_vec(),
                }),
                "32FC1" => inverse_depth(&c.data[..DEPTH_HEADER], png),
                other => Err(format!(
                    "depth: compressedDepth of {other:?} (16UC1 or 32FC1 expected)"
                )),
            }
        }
        Received::Raw(i) => {
            let (encoding, bpp) = match i.encoding.as_str() {
                "16UC1" | "mono16" => (proto::DepthEncoding::Uint16Millimeters, 2),
                "32FC1" => (proto::DepthEncoding::Float32Meters, 4),
                "rgb8" | "bgr8" | "rgba8" | "bgra8" | "mono8" => {
                    return Err(format!(
                        "depth: the image is {} (a colour encoding): depth_topic names a colour topic",
                        i.encoding
                    ))
                }
                other => {
                    return Err(format!(
                        "depth: encoding {other:?} is not supported (16UC1 millimetres, 32FC1 metres, or the /compressedDepth topic)"
                    ))
                }
            };
            let mut data = packed_rows(i, bpp)?;
            if i.is_bigendian != 0 {
                data.chunks_exact_mut(bpp).for_each(|p| p.reverse());
            }
            Ok(proto::Depth {
                width: i.width,
                height: i.height,
                encoding: encoding as i32,
                data,
            })
        }
    }
}

/// A 32FC1 compressedDepth: a 16-bit PNG of quantized inverse depth `q = a / d + b`, decoded as
/// `d = a / (q - b)` with `a`, `b` from the header (`depthParam`); q = 0 is missing depth.
fn inverse_depth(header: &[u8], png_file: &[u8]) -> Result<proto::Depth, String> {
    let a = f32::from_le_bytes(header[4..8].try_into().unwrap_or_default());
    let b = f32::from_le_bytes(header[8..12].try_into().unwrap_or_default());
    let bad = |e: String| format!("depth: compressedDepth 32FC1 PNG: {e}");
    let mut reader = png::Decoder::new(std::io::Cursor::new(png_file))
        .read_info()
        .map_err(|e| bad(e.to_string()))?;
    let mut buf = vec![
        0;
        reader
            .output_buffer_size()
            .ok_or_else(|| bad("too large".into()))?
    ];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| bad(e.to_string()))?;
    if info.bit_depth != png::BitDepth::Sixteen || info.color_type != png::ColorType::Grayscale {
        return Err(bad(format!(
            "{:?} {:?}, a 16-bit grey image expected",
            info.color_type, info.bit_depth
        )));
    }
    let data: Vec<u8> = buf[..info.buffer_size()]
        .chunks_exact(2)
        .flat_map(|p| {
            let q = f32::from(u16::from_be_bytes([p[0], p[1]]));
            let d = if q == 0.0 { 0.0 } else { a / (q - b) };
            d.to_le_bytes()
        })
        .collect();
    Ok(proto::Depth {
        width: info.width,
        height: info.height,
        encoding: proto::DepthEncoding::Float32Meters as i32,
        data,
    })
}

/// The intrinsics of a CameraInfo for an image of `size` (width, height).
pub fn intrinsics(info: &msgs::CameraInfo, size: (u32, u32)) -> Result<proto::Intrinsics, String> {
    if (info.width, info.height) != size && size != (0, 0) {
        return Err(format!(
            "camera_info is {}x{} but the image is {}x{}: info_topic belongs to another camera or resolution",
            info.width, info.height, size.0, size.1
        ));
    }
    if info.binning_x > 1 || info.binning_y > 1 || info.roi.width != 0 {
        return Err("camera_info: binning or a region of interest is not supported".into());
    }
    let [fx, _, cx, _, fy, cy, ..] = info.k;
    if fx <= 0.0 || fy <= 0.0 {
        return Err(format!(
            "camera_info: focal lengths {fx}, {fy} (an uncalibrated camera publishes zeros)"
        ));
    }
    let d = &info.d;
    let distortion = if d.iter().all(|c| *c == 0.0) {
        Vec::new()
    } else if matches!(
        info.distortion_model.as_str(),
        "plumb_bob" | "rational_polynomial"
    ) && (4..=5).contains(&d.len())
        || info.distortion_model == "rational_polynomial" && d[5..].iter().all(|c| *c == 0.0)
    {
        d[..d.len().min(5)].to_vec()
    } else {
        return Err(format!(
            "camera_info: distortion model {:?} with {} coefficients is not supported (plumb_bob, or a rectified image_rect topic)",
            info.distortion_model,
            d.len()
        ));
    };
    Ok(proto::Intrinsics {
        fx,
        fy,
        cx,
        cy,
        distortion,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(encoding: &str, w: u32, h: u32, step: u32, data: Vec<u8>) -> Received {
        Received::Raw(msgs::Image {
            encoding: encoding.into(),
            width: w,
            height: h,
            step,
            data,
            ..Default::default()
        })
    }

    #[test]
    fn colour_orders_and_padding() {
        // 2x1 bgra8 with 4 bytes of row padding.
        let m = image("bgra8", 2, 1, 12, vec![3, 2, 1, 9, 6, 5, 4, 9, 0, 0, 0, 0]);
        let c = colour(&m).unwrap();
        assert_eq!(c.data, vec![1, 2, 3, 4, 5, 6]);
        assert_eq!(c.encoding, proto::ImageEncoding::RawRgb8 as i32);
        let e = colour(&image("16UC1", 1, 1, 2, vec![0, 0])).unwrap_err();
        assert!(e.contains("depth topic"), "{e}");
        let e = colour(&image("rgb8", 4, 1, 12, vec![0; 6])).unwrap_err();
        assert!(e.contains("row needs"), "{e}");
    }

    #[test]
    fn depth_big_endian_and_compressed_header() {
        let d = depth(&image("16UC1", 1, 1, 2, vec![0x03, 0xE8])).unwrap();
        assert_eq!(d.data, vec![0x03, 0xE8]);
        let m = msgs::Image {
            is_bigendian: 1,
            ..match image("16UC1", 1, 1, 2, vec![0x03, 0xE8]) {
                Received::Raw(i) => i,
                _ => unreachable!(),
            }
        };
        assert_eq!(
            u16::from_le_bytes(
                depth(&Received::Raw(m)).unwrap().data[..2]
                    .try_into()
                    .unwrap()
            ),
            1000
        );
        let mut data = vec![0; 12];
        data.extend_from_slice(b"\x89PNG rest");
        let c = depth(&Received::Compressed(msgs::CompressedImage {
            format: "16UC1; compressedDepth png".into(),
            data,
            ..Default::default()
        }))
        .unwrap();
        assert!(c.data.starts_with(b"\x89PNG"));
        assert_eq!(c.encoding, proto::DepthEncoding::Png16Millimeters as i32);
    }

    #[test]
    fn inverse_depth_png_decodes_to_metres() {
        // depth_quantization 100, depth_max 10: a = 10100, b = -1009; 2 m -> q = 5050 - 1009.
        let (a, b) = (10100.0f32, -1009.0f32);
        let q = (a / 2.0 + b).round() as u16;
        let mut file = Vec::new();
        {
            let mut e = png::Encoder::new(&mut file, 2, 1);
            e.set_color(png::ColorType::Grayscale);
            e.set_depth(png::BitDepth::Sixteen);
            let mut w = e.write_header().unwrap();
            let px: Vec<u8> = [q, 0].iter().flat_map(|v| v.to_be_bytes()).collect();
            w.write_image_data(&px).unwrap();
        }
        let mut data = 0i32.to_le_bytes().to_vec();
        data.extend(a.to_le_bytes());
        data.extend(b.to_le_bytes());
        data.extend(file);
        let d = depth(&Received::Compressed(msgs::CompressedImage {
            format: "32FC1; compressedDepth".into(),
            data,
            ..Default::default()
        }))
        .unwrap();
        let m: Vec<f32> = d
            .data
            .chunks_exact(4)
            .map(|p| f32::from_le_bytes(p.try_into().unwrap()))
            .collect();
        assert!((m[0] - 2.0).abs() < 1e-3, "{m:?}");
        assert_eq!(m[1], 0.0);
    }

    #[test]
    fn camera_info_of_another_camera_is_named() {
        let info = msgs::CameraInfo {
            width: 640,
            height: 480,
            k: [525.0, 0.0, 320.0, 0.0, 525.0, 240.0, 0.0, 0.0, 1.0],
            distortion_model: "plumb_bob".into(),
            d: vec![0.0; 5],
            ..Default::default()
        };
        let k = intrinsics(&info, (640, 480)).unwrap();
        assert_eq!((k.fx, k.cy), (525.0, 240.0));
        assert!(k.distortion.is_empty());
        let e = intrinsics(&info, (1280, 720)).unwrap_err();
        assert!(e.contains("another camera"), "{e}");
    }
}
