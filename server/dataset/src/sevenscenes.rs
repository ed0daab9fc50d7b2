//! RGB-D sequences in the 7-Scenes layout (Microsoft 7-Scenes; also 12-Scenes and the demo data of
//! tsdf-fusion), read as they are distributed:
//!
//! ```text
//! DIR/frame-000000.color.png|jpg   colour, 8-bit
//! DIR/frame-000000.depth.png       depth, 16-bit millimetres, 0 and 65535 = no measurement
//! DIR/frame-000000.pose.txt        4x4 world_from_camera, row-major (optical axes: x right, y down,
//!                                  z forward); a non-finite pose (7-Scenes marks lost tracking so)
//!                                  is no pose
//! DIR/camera-intrinsics.txt        3x3 K of the camera the poses and depth belong to, optional
//! ```
//!
//! Frames carry no stamps: frame `i` is stamped `i / FRAME_RATE_HZ` (the Kinect's 30 Hz). The depth
//! of raw 7-Scenes frames is the depth camera's, not registered to colour: the caller registers it
//! ([`crate::depth_camera`]) and moves the poses to the colour camera ([`crate::recording`]).

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use pntr_core::{DepthMap, Intrinsics, RgbImage};

use crate::DatasetError;

/// Stamps of frames, which the layout does not carry: the frame rate of the Kinect the dataset was
/// recorded with.
pub const FRAME_RATE_HZ: f64 = 30.0;
/// Depth PNG units per metre (millimetres).
pub const DEPTH_UNITS_PER_M: f64 = 1000.0;
/// The file of a 7-Scenes folder that holds its depth camera's 3x3 camera matrix.
pub const CAMERA_INTRINSICS: &str = "camera-intrinsics.txt";

/// The camera of a `camera-intrinsics.txt` file (a 3x3 matrix K, row-major, whitespace-separated)
/// for images of `size` (width, height) pixels, without distortion.
///
/// Errors name the file: unreadable, not nine numbers, or not a camera matrix.
pub fn camera_intrinsics(path: &Path, size: (u32, u32)) -> Result<Intrinsics, DatasetError> {
    let k = numbers(path, 9)?;
    let i = Intrinsics {
        fx: k[0],
        fy: k[4],
        cx: k[2],
        cy: k[5],
        width: size.0,
        height: size.1,
        distortion: [0.0; 5],
    };
    i.validate()
        .map_err(|e| layout(path, format!("not a camera matrix: {e}")))?;
    Ok(i)
}

/// One frame's files.
#[derive(Debug, Clone)]
pub struct SevenScenesFrame {
    /// Frame number (`frame-NNNNNN`).
    pub index: usize,
    /// Colour image.
    pub color: PathBuf,
    /// Depth image.
    pub depth: PathBuf,
    /// `world_from_camera` from the pose file, `None` when it is not a finite rigid transform.
    pub world_from_camera: Option<Isometry3<f64>>,
}

/// A sequence folder in the 7-Scenes layout.
#[derive(Debug, Clone)]
pub struct SevenScenes {
    /// The folder.
    pub root: PathBuf,
    /// Frames in order of their numbers.
    pub frames: Vec<SevenScenesFrame>,
    /// `camera-intrinsics.txt`, when present: fx, fy, cx, cy (the size taken from the first depth
    /// image).
    pub intrinsics: Option<Intrinsics>,
    /// Depth units per metre ([`DEPTH_UNITS_PER_M`] unless the caller knows better).
    pub depth_units_per_m: f64,
}

fn layout(path: &Path, problem: impl Into<String>) -> DatasetError {
    DatasetError::Layout {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

/// True when `dir` holds frames in the 7-Scenes layout (a `frame-*.pose.txt`).
pub fn is_seven_scenes(dir: &Path) -> bool {
    dir.is_dir()
        && std::fs::read_dir(dir).is_ok_and(|d| {
            d.filter_map(|e| e.ok()).any(|e| {
                let n = e.file_name();
                let n = n.to_string_lossy();
                n.starts_with("frame-") && n.ends_with(".pose.txt")
            })
        })
}

fn numbers(path: &Path, expected: usize) -> Result<Vec<f64>, DatasetError> {
    let text =
        std::fs::read_to_string(path).map_err(|e| layout(path, format!("cannot read: {e}")))?;
    let v: Vec<f64> = text
        .split_whitespace()
        .map(|t| {
            t.parse::<f64>()
                .map_err(|_| layout(path, format!("`{t}` is not a number")))
        })
        .collect::<Result<_, _>>()?;
    if v.len() != expected {
        return Err(layout(
            path,
            format!("{} numbers, expected {expected}", v.len()),
        ));
    }
    Ok(v)
}

/// A 4x4 row-major pose as a rigid transform; `None` when not finite. Errors when finite but not
/// rigid (a rotation block whose rows are not orthonormal within 1e-3, or a last row other than
/// 0 0 0 1).
fn pose(path: &Path, m: &[f64]) -> Result<Option<Isometry3<f64>>, DatasetError> {
    if m.iter().any(|x| !x.is_finite()) {
        return Ok(None);
    }
    let r = Matrix3::new(m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]);
    let ortho = (r * r.transpose() - Matrix3::identity()).abs().max();
    let last = [m[12], m[13], m[14], m[15] - 1.0];
    if ortho > 1e-3 || r.determinant() < 0.0 || last.iter().any(|x| x.abs() > 1e-6) {
        return Err(layout(
            path,
            format!("not a rigid 4x4 world_from_camera (rotation rows off orthonormal by {ortho:.2e}, last row {:?})", &m[12..16]),
        ));
    }
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Ok(Some(Isometry3::from_parts(
        Translation3::new(m[3], m[7], m[11]),
        rot,
    )))
}

impl SevenScenes {
    /// Read a folder's file names, poses and intrinsics; images are read by [`SevenScenes::load`].
    /// Errors name the file: a frame without its depth image or pose, a pose that is not 16
    /// numbers or not rigid, an intrinsics file that is not a 3x3 matrix, no frames at all.
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        let entries = std::fs::read_dir(root)
            .map_err(|e| layout(root, format!("cannot list the folder: {e}")))?;
        let mut indices: Vec<usize> = entries
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let n = e.file_name().to_string_lossy().to_string();
                n.strip_prefix("frame-")?
                    .strip_suffix(".pose.txt")?
                    .parse()
                    .ok()
            })
            .collect();
        indices.sort_unstable();
        if indices.is_empty() {
            return Err(layout(
                root,
                "no frame-NNNNNN.pose.txt (expected the 7-Scenes layout: frame-NNNNNN.color.png|jpg, .depth.png, .pose.txt)",
            ));
        }
        let mut frames = Vec::with_capacity(indices.len());
        for index in indices {
            let stem = root.join(format!("frame-{index:06}"));
            let with = |s: &str| PathBuf::from(format!("{}.{s}", stem.display()));
            let color = [with("color.png"), with("color.jpg")]
                .into_iter()
                .find(|p| p.is_file())
                .ok_or_else(|| layout(&with("color.png"), "missing (nor .color.jpg)"))?;
            let depth = with("depth.png");
            if !depth.is_file() {
                return Err(layout(&depth, "missing: every frame needs its depth image"));
            }
            let pose_path = with("pose.txt");
            let world_from_camera = pose(&pose_path, &numbers(&pose_path, 16)?)?;
            frames.push(SevenScenesFrame {
                index,
                color,
                depth,
                world_from_camera,
            });
        }
        let k_path = root.join(CAMERA_INTRINSICS);
        let intrinsics = if k_path.is_file() {
            let (w, h) = image::image_dimensions(&frames[0].depth)
                .map_err(|e| layout(&frames[0].depth, format!("cannot read its size: {e}")))?;
            Some(camera_intrinsics(&k_path, (w, h))?)
        } else {
            None
        };
        Ok(Self {
            root: root.to_path_buf(),
            frames,
            intrinsics,
            depth_units_per_m: DEPTH_UNITS_PER_M,
        })
    }

    /// Stamp of frame `i` (the `i`-th in order), seconds: its number over [`FRAME_RATE_HZ`].
    pub fn timestamp(&self, i: usize) -> f64 {
        self.frames[i].index as f64 / FRAME_RATE_HZ
    }

    /// Decode frame `i`: colour, and depth in metres in the depth image's own pixels (0 and 65535 are
    /// no measurement). Errors name the file.
    pub fn load(&self, i: usize) -> Result<(RgbImage, DepthMap), DatasetError> {
        let f = &self.frames[i];
        let rgb = image::open(&f.color)
            .map_err(|e| layout(&f.color, format!("cannot decode the colour image: {e}")))?
            .to_rgb8();
        let (w, h) = rgb.dimensions();
        let depth = match image::open(&f.depth)
            .map_err(|e| layout(&f.depth, format!("cannot decode the depth image: {e}")))?
        {
            image::DynamicImage::ImageLuma16(d) => d,
            other => {
                return Err(layout(
                    &f.depth,
                    format!(
                        "depth must be a 16-bit single-channel PNG (millimetres), not {:?}",
                        other.color()
                    ),
                ))
            }
        };
        let (dw, dh) = depth.dimensions();
        let scale = self.depth_units_per_m as f32;
        let metres = depth
            .into_raw()
            .into_iter()
            .map(|d| {
                if d == 0 || d == u16::MAX {
                    0.0
                } else {
                    d as f32 / scale
                }
            })
            .collect();
        Ok((
            RgbImage {
                width: w,
                height: h,
                data: rgb.into_raw(),
            },
            DepthMap::from_metres(dw, dh, metres).map_err(|e| layout(&f.depth, e.to_string()))?,
        ))
    }
}
