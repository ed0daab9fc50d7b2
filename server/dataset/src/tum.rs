//! RGB-D sequences in the TUM RGB-D benchmark's folder layout: what a robot recorded while driving.
//!
//! ```text
//! DIR/rgb/<timestamp>.png        colour, 8-bit RGB
//! DIR/depth/<timestamp>.png      depth, 16-bit, `DEPTH_UNITS_PER_M` units per metre, 0 = no measurement
//! DIR/rgb.txt, DIR/depth.txt     "timestamp filename" per line, `#` comments
//! DIR/groundtruth.txt            "timestamp tx ty tz qx qy qz qw" (world_from_camera, optical camera
//!                                axes: x right, y down, z forward), optional
//! DIR/calibration.txt            "fx fy cx cy [k1 k2 p1 p2 [k3]]", optional when the caller knows the camera
//! ```
//!
//! Colour and depth frames are paired by nearest timestamp (at most [`MAX_PAIR_GAP_S`] apart, as the
//! benchmark's `associate.py` does), ground truth likewise. Poses follow the TUM convention: the camera's
//! optical axes (OpenCV's: x right, y down, z forward), whatever the world frame; `pntr synth
//! --trajectory-seconds` writes its drives that way too (in the scene's y-up world frame), and readers
//! convert to a map's own axes where they differ ([`pntr_core::convert_axes`]).

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use pntr_core::{DepthMap, Intrinsics, RgbImage};

use crate::DatasetError;

/// Depth PNG units per metre (the TUM benchmark's factor).
pub const DEPTH_UNITS_PER_M: f64 = 5000.0;
/// Largest gap between paired colour, depth and ground-truth timestamps, seconds.
pub const MAX_PAIR_GAP_S: f64 = 0.02;

/// One frame of a sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct TumFrame {
    /// Timestamp of the colour image, seconds.
    pub timestamp: f64,
    /// Colour image file.
    pub rgb: PathBuf,
    /// Depth image file.
    pub depth: PathBuf,
    /// Ground-truth `world_from_camera` (optical camera axes), when the sequence has it for this time.
    pub world_from_camera: Option<Isometry3<f64>>,
}

/// A sequence on disk: its camera and its paired frames in time order.
#[derive(Debug, Clone)]
pub struct TumSequence {
    /// The folder.
    pub root: PathBuf,
    /// The camera (from calibration.txt; `None` when the folder has none).
    pub intrinsics: Option<Intrinsics>,
    /// Frames with both colour and depth, in time order.
    pub frames: Vec<TumFrame>,
    /// Depth PNG units per metre ([`DEPTH_UNITS_PER_M`] unless the caller knows better: 1000 for
    /// millimetre PNGs, 4000 for a sensor with 0.25 mm units).
    pub depth_units_per_m: f64,
}

fn layout(path: &Path, problem: impl Into<String>) -> DatasetError {
    DatasetError::Layout {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

fn read_text(path: &Path) -> Result<String, DatasetError> {
    std::fs::read_to_string(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Non-comment lines split on whitespace, with their 1-based line numbers.
fn records(text: &str) -> impl Iterator<Item = (usize, Vec<&str>)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
        .map(|(i, l)| (i, l.split_whitespace().collect()))
}

fn number(path: &Path, line: usize, field: &str, s: &str) -> Result<f64, DatasetError> {
    s.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| {
            layout(
                path,
                format!("line {line}: {field} `{s}` is not a finite number"),
            )
        })
}

/// A "timestamp filename" list (rgb.txt, depth.txt), sorted by time.
fn file_list(root: &Path, name: &str) -> Result<Vec<(f64, PathBuf)>, DatasetError> {
    let path = root.join(name);
    let mut out = Vec::new();
    for (line, f) in records(&read_text(&path)?) {
        if f.len() < 2 {
            return Err(layout(
                &path,
                format!("line {line}: expected `timestamp filename`"),
            ));
        }
        out.push((number(&path, line, "timestamp", f[0])?, root.join(f[1])));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(out)
}

/// groundtruth.txt: (timestamp, world_from_camera), sorted by time.
fn ground_truth(path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, DatasetError> {
    let mut out = Vec::new();
    for (line, f) in records(&read_text(path)?) {
        if f.len() != 8 {
            return Err(layout(
                path,
                format!(
                    "line {line}: expected `timestamp tx ty tz qx qy qz qw`, got {} values",
                    f.len()
                ),
            ));
        }
        let v: Vec<f64> = f
            .iter()
            .zip(["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"])
            .map(|(s, name)| number(path, line, name, s))
            .collect::<Result<_, _>>()?;
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        if (q.norm() - 1.0).abs() > 1e-3 {
            return Err(layout(
                path,
                format!(
                    "line {line}: quaternion norm {:.4}, expected a unit quaternion",
                    q.norm()
                ),
            ));
        }
        out.push((
            v[0],
            Isometry3::from_parts(
                Translation3::new(v[1], v[2], v[3]),
                UnitQuaternion::from_quaternion(q),
            ),
        ));
    }
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    Ok(out)
}

/// Longest gap between two poses of a trajectory that [`Trajectory::at`] interpolates across, seconds
/// (a SLAM output at 5-30 Hz; a longer gap is a lost track, not a pose to invent).
pub const MAX_INTERPOLATION_GAP_S: f64 = 0.5;

/// A camera trajectory in the TUM format (`timestamp tx ty tz qx qy qz qw`, world_from_camera, optical
/// axes): a SLAM system's output or a sequence's groundtruth.txt, looked up at any stamp.
#[derive(Debug, Clone, Default)]
pub struct Trajectory {
    poses: Vec<(f64, Isometry3<f64>)>,
}

impl Trajectory {
    /// Read a TUM trajectory file. Errors name the file and line (a malformed line, a quaternion that
    /// is not unit length, no pose at all).
    pub fn read(path: &Path) -> Result<Self, DatasetError> {
        let poses = ground_truth(path)?;
        if poses.is_empty() {
            return Err(layout(
                path,
                "no pose (expected lines `timestamp tx ty tz qx qy qz qw`)",
            ));
        }
        Ok(Self { poses })
    }

    /// A trajectory of `(stamp seconds, world_from_camera)` samples in any order.
    pub fn from_poses(mut poses: Vec<(f64, Isometry3<f64>)>) -> Self {
        poses.sort_by(|a, b| a.0.total_cmp(&b.0));
        Self { poses }
    }

    /// Samples.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// True without samples.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// First and last stamp, seconds.
    pub fn span(&self) -> Option<(f64, f64)> {
        Some((self.poses.first()?.0, self.poses.last()?.0))
    }

    /// The pose at `t` seconds: interpolated between the samples around it (linear in translation,
    /// slerp in rotation) when they are at most [`MAX_INTERPOLATION_GAP_S`] apart, else the nearest
    /// sample within [`MAX_PAIR_GAP_S`]; `None` outside the trajectory or inside a longer gap.
    pub fn at(&self, t: f64) -> Option<Isometry3<f64>> {
        self.at_within(t, MAX_INTERPOLATION_GAP_S)
    }

    /// [`Trajectory::at`] interpolating across gaps of at most `max_gap_s` seconds.
    pub fn at_within(&self, t: f64, max_gap_s: f64) -> Option<Isometry3<f64>> {
        let p = &self.poses;
        let i = p.partition_point(|e| e.0 < t);
        if i < p.len() && (p[i].0 - t).abs() < 1e-9 {
            return Some(p[i].1);
        }
        if i > 0 && i < p.len() && p[i].0 - p[i - 1].0 <= max_gap_s {
            let (t0, a) = p[i - 1];
            let (t1, b) = p[i];
            let u = ((t - t0) / (t1 - t0).max(1e-12)).clamp(0.0, 1.0);
            return Some(interpolate(&a, &b, u));
        }
        nearest(p, t).map(|j| p[j].1)
    }
}

/// The pose a fraction `u` (0..1) of the way from `a` to `b`: linear translation, slerp rotation.
pub fn interpolate(a: &Isometry3<f64>, b: &Isometry3<f64>, u: f64) -> Isometry3<f64> {
    let t = a.translation.vector.lerp(&b.translation.vector, u);
    let r = a
        .rotation
        .try_slerp(&b.rotation, u, 1e-12)
        .unwrap_or(if u < 0.5 { a.rotation } else { b.rotation });
    Isometry3::from_parts(Translation3::from(t), r)
}

/// Index of the entry of `sorted` (by time, seconds) nearest to `t`, if within [`MAX_PAIR_GAP_S`].
pub(crate) fn nearest<T>(sorted: &[(f64, T)], t: f64) -> Option<usize> {
    let i = sorted.partition_point(|e| e.0 < t);
    [i.checked_sub(1), (i < sorted.len()).then_some(i)]
        .into_iter()
        .flatten()
        .min_by(|&a, &b| (sorted[a].0 - t).abs().total_cmp(&(sorted[b].0 - t).abs()))
        .filter(|&j| (sorted[j].0 - t).abs() <= MAX_PAIR_GAP_S)
}

impl TumSequence {
    /// Read a sequence folder's lists; the images are read by [`TumSequence::load`].
    ///
    /// Errors name the file and line: a missing rgb.txt/depth.txt, a malformed line, a calibration
    /// that is not `fx fy cx cy [k1 k2 p1 p2 [k3]]`, or no colour frame with a depth frame within
    /// [`MAX_PAIR_GAP_S`].
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        if !root.exists() {
            return Err(layout(
                root,
                "no such file or folder (expected a TUM RGB-D sequence folder, a 7-Scenes folder, a ROS 2 bag folder or an .mcap file)",
            ));
        }
        if !root.is_dir() {
            return Err(layout(
                root,
                "not a folder (expected a TUM RGB-D sequence: rgb.txt, depth.txt, rgb/, depth/)",
            ));
        }
        if !root.join("rgb.txt").is_file() {
            let mcap = std::fs::read_dir(root).is_ok_and(|d| {
                d.filter_map(|e| e.ok()).any(|e| {
                    e.path()
                        .extension()
                        .is_some_and(|x| x.eq_ignore_ascii_case("mcap"))
                })
            });
            if mcap {
                return Err(layout(
                    root,
                    "no rgb.txt (not a TUM RGB-D sequence), and .mcap files without metadata.yaml (not a rosbag2 folder): give the .mcap file itself, or the rosbag2 folder with its metadata.yaml",
                ));
            }
        }
        let rgb = file_list(root, "rgb.txt")?;
        let depth = file_list(root, "depth.txt")?;
        let gt_path = root.join("groundtruth.txt");
        let gt = if gt_path.is_file() {
            ground_truth(&gt_path)?
        } else {
            Vec::new()
        };
        let calib = root.join("calibration.txt");
        let intrinsics = if calib.is_file() {
            Some(Self::calibration(
                &calib,
                rgb.first().map(|f| f.1.as_path()),
            )?)
        } else {
            None
        };
        let frames: Vec<TumFrame> = rgb
            .iter()
            .filter_map(|(t, path)| {
                let d = nearest(&depth, *t)?;
                Some(TumFrame {
                    timestamp: *t,
                    rgb: path.clone(),
                    depth: depth[d].1.clone(),
                    world_from_camera: nearest(&gt, *t).map(|g| gt[g].1),
                })
            })
            .collect();
        if frames.is_empty() {
            return Err(layout(
                root,
                format!(
                    "no colour frame has a depth frame within {MAX_PAIR_GAP_S} s ({} colour, {} depth listed)",
                    rgb.len(),
                    depth.len()
                ),
            ));
        }
        Ok(Self {
            root: root.to_path_buf(),
            intrinsics,
            frames,
            depth_units_per_m: DEPTH_UNITS_PER_M,
        })
    }

    /// calibration.txt: `fx fy cx cy [k1 k2 p1 p2 [k3]]` for images of the size of `first_image`.
    fn calibration(path: &Path, first_image: Option<&Path>) -> Result<Intrinsics, DatasetError> {
        let text = read_text(path)?;
        let Some((line, f)) = records(&text).next() else {
            return Err(layout(
                path,
                "empty (expected `fx fy cx cy [k1 k2 p1 p2 [k3]]`)",
            ));
        };
        if ![4, 8, 9].contains(&f.len()) {
            return Err(layout(
                path,
                format!(
                    "line {line}: expected `fx fy cx cy [k1 k2 p1 p2 [k3]]`, got {} values",
                    f.len()
                ),
            ));
        }
        let v: Vec<f64> = f
            .iter()
            .map(|s| number(path, line, "value", s))
            .collect::<Result<_, _>>()?;
        let (width, height) = match first_image {
            Some(p) => image::image_dimensions(p)
                .map_err(|e| layout(p, format!("cannot read the image size: {e}")))?,
            None => return Err(layout(path, "no image listed to take the size from")),
        };
        let mut k = Intrinsics {
            fx: v[0],
            fy: v[1],
            cx: v[2],
            cy: v[3],
            width,
            height,
            ..Intrinsics::hpointloc()
        };
        for (i, d) in v[4..].iter().enumerate() {
            k.distortion[i] = *d;
        }
        k.validate()
            .map_err(|e| layout(path, format!("line {line}: {e}")))?;
        Ok(k)
    }

    /// Decode frame `i`: colour (8-bit RGB or RGBA PNG/JPEG) and depth (16-bit PNG in
    /// [`TumSequence::depth_units_per_m`], 0 = missing) in metres. Errors name the file.
    pub fn load(&self, i: usize) -> Result<(RgbImage, DepthMap), DatasetError> {
        let f = &self.frames[i];
        let rgb = image::open(&f.rgb)
            .map_err(|e| layout(&f.rgb, format!("cannot decode the colour image: {e}")))?
            .to_rgb8();
        let (w, h) = rgb.dimensions();
        let depth = image::open(&f.depth)
            .map_err(|e| layout(&f.depth, format!("cannot decode the depth image: {e}")))?;
        let depth = match depth {
            image::DynamicImage::ImageLuma16(d) => d,
            other => {
                return Err(layout(
                    &f.depth,
                    format!(
                        "depth must be a 16-bit single-channel PNG ({DEPTH_UNITS_PER_M} per metre), not {:?}",
                        other.color()
                    ),
                ))
            }
        };
        if depth.dimensions() != (w, h) {
            return Err(layout(
                &f.depth,
                format!(
                    "depth is {:?}, the colour image {:?}",
                    depth.dimensions(),
                    (w, h)
                ),
            ));
        }
        Ok((
            RgbImage {
                width: w,
                height: h,
                data: rgb.into_raw(),
            },
            DepthMap {
                width: w,
                height: h,
                data: depth
                    .into_raw()
                    .into_iter()
                    .map(|v| (v as f64 / self.depth_units_per_m) as f32)
                    .collect(),
            },
        ))
    }
}

/// A frame to write with [`write_sequence`].
#[derive(Debug, Clone)]
pub struct SequenceFrame {
    /// Seconds.
    pub timestamp: f64,
    /// Colour.
    pub rgb: RgbImage,
    /// Depth in metres (0 = missing; stored rounded to 1/5000 m, at most 13.1 m).
    pub depth: DepthMap,
    /// Ground-truth `world_from_camera`, optical camera axes (the TUM convention).
    pub world_from_camera: Isometry3<f64>,
}

/// One line of groundtruth.txt for `pose` at `t` (TUM order: tx ty tz qx qy qz qw).
pub fn ground_truth_line(t: f64, pose: &Isometry3<f64>) -> String {
    let p = pose.translation.vector;
    let [w, x, y, z] = pntr_core::pose::canonical_wxyz(&pose.rotation);
    format!(
        "{t:.6} {:.6} {:.6} {:.6} {x:.7} {y:.7} {z:.7} {w:.7}",
        p.x, p.y, p.z
    )
}

/// Write a sequence into `dir` in the TUM layout (through a temporary folder renamed into place, so
/// an interrupted write leaves no half sequence). `k` goes to calibration.txt.
pub fn write_sequence(
    dir: &Path,
    frames: &[SequenceFrame],
    k: &Intrinsics,
) -> Result<(), DatasetError> {
    let name = dir
        .file_name()
        .ok_or_else(|| layout(dir, "no folder name"))?
        .to_string_lossy()
        .to_string();
    let parent = dir.parent().unwrap_or(Path::new("."));
    let tmp = parent.join(format!(".{name}.partial-{}", std::process::id()));
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| DatasetError::Io { path, source }
    };
    let _ = std::fs::remove_dir_all(&tmp);
    for sub in ["rgb", "depth"] {
        std::fs::create_dir_all(tmp.join(sub)).map_err(io(&tmp.join(sub)))?;
    }
    let header = |what: &str| format!("# {what}\n# file: '{name}'\n# timestamp filename\n");
    let (mut rgb_txt, mut depth_txt) = (header("color images"), header("depth maps"));
    let mut gt = String::from(
        "# ground truth trajectory (world_from_camera)\n# timestamp tx ty tz qx qy qz qw\n",
    );
    for f in frames {
        let file = format!("{:.6}.png", f.timestamp);
        let rgb_path = tmp.join("rgb").join(&file);
        image::RgbImage::from_raw(f.rgb.width, f.rgb.height, f.rgb.data.clone())
            .ok_or_else(|| layout(&rgb_path, "colour buffer does not match its size"))?
            .save_with_format(&rgb_path, image::ImageFormat::Png)
            .map_err(|e| layout(&rgb_path, e.to_string()))?;
        let units: Vec<u16> = f
            .depth
            .data
            .iter()
            .map(|&d| {
                if d.is_finite() && d > 0.0 {
                    (d as f64 * DEPTH_UNITS_PER_M).round().min(65535.0) as u16
                } else {
                    0
                }
            })
            .collect();
        let depth_path = tmp.join("depth").join(&file);
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(f.depth.width, f.depth.height, units)
            .ok_or_else(|| layout(&depth_path, "depth buffer does not match its size"))?
            .save_with_format(&depth_path, image::ImageFormat::Png)
            .map_err(|e| layout(&depth_path, e.to_string()))?;
        rgb_txt += &format!("{:.6} rgb/{file}\n", f.timestamp);
        depth_txt += &format!("{:.6} depth/{file}\n", f.timestamp);
        gt += &ground_truth_line(f.timestamp, &f.world_from_camera);
        gt.push('\n');
    }
    let mut calib = format!("{} {} {} {}", k.fx, k.fy, k.cx, k.cy);
    if k.is_distorted() {
        for d in k.distortion {
            calib += &format!(" {d}");
        }
    }
    for (file, text) in [
        ("rgb.txt", rgb_txt),
        ("depth.txt", depth_txt),
        ("groundtruth.txt", gt),
        ("calibration.txt", calib + "\n"),
    ] {
        let p = tmp.join(file);
        std::fs::write(&p, text).map_err(io(&p))?;
    }
    let old = parent.join(format!(".{name}.old-{}", std::process::id()));
    if dir.exists() {
        std::fs::rename(dir, &old).map_err(io(dir))?;
    }
    std::fs::rename(&tmp, dir).map_err(io(dir))?;
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(t: f64, shade: u8) -> SequenceFrame {
        SequenceFrame {
            timestamp: t,
            rgb: RgbImage {
                width: 4,
                height: 2,
                data: vec![shade; 24],
            },
            depth: DepthMap {
                width: 4,
                height: 2,
                data: vec![0.0, 1.0, 2.5, 10.0, 0.0002, f32::NAN, -1.0, 20.0],
            },
            world_from_camera: Isometry3::from_parts(
                Translation3::new(1.0, 1.25, -2.0 - t),
                UnitQuaternion::from_euler_angles(0.0, t, 0.0),
            ),
        }
    }

    #[test]
    fn a_written_sequence_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let seq = dir.path().join("synth000");
        let frames = [frame(0.0, 10), frame(0.1, 20), frame(0.2, 30)];
        let k = Intrinsics {
            width: 4,
            height: 2,
            fx: 2.0,
            fy: 2.0,
            cx: 1.5,
            cy: 0.5,
            ..Intrinsics::hpointloc()
        };
        write_sequence(&seq, &frames, &k).unwrap();
        let s = TumSequence::open(&seq).unwrap();
        assert_eq!(s.frames.len(), 3);
        let back = s.intrinsics.unwrap();
        assert_eq!(
            (back.fx, back.cx, back.width, back.height),
            (2.0, 1.5, 4, 2)
        );
        for (i, f) in frames.iter().enumerate() {
            let (rgb, depth) = s.load(i).unwrap();
            assert_eq!(rgb.data, f.rgb.data);
            // Quantised to 1/5000 m; invalid values become 0; beyond 13.1 m saturates.
            let want = [0.0, 1.0, 2.5, 10.0, 0.0002, 0.0, 0.0, 13.107];
            for (d, w) in depth.data.iter().zip(want) {
                assert!((d - w).abs() < 1e-3, "{d} vs {w}");
            }
            let gt = s.frames[i].world_from_camera.unwrap();
            assert!((gt.translation.vector - f.world_from_camera.translation.vector).norm() < 1e-5);
            assert!(gt.rotation.angle_to(&f.world_from_camera.rotation) < 1e-5);
            assert!((s.frames[i].timestamp - f.timestamp).abs() < 1e-9);
        }
    }

    #[test]
    fn mistakes_name_the_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let seq = dir.path().join("s");
        write_sequence(&seq, &[frame(0.0, 1)], &Intrinsics::from_fov(4, 2, 90.0)).unwrap();
        std::fs::write(seq.join("groundtruth.txt"), "0.0 1 2 3 0 0 0\n").unwrap();
        let e = TumSequence::open(&seq).unwrap_err().to_string();
        assert!(
            e.contains("groundtruth.txt") && e.contains("line 1") && e.contains("7 values"),
            "{e}"
        );
        std::fs::write(seq.join("groundtruth.txt"), "0.0 1 2 3 0 0 0 2\n").unwrap();
        let e = TumSequence::open(&seq).unwrap_err().to_string();
        assert!(e.contains("unit quaternion"), "{e}");
        std::fs::remove_file(seq.join("groundtruth.txt")).unwrap();
        std::fs::write(seq.join("depth.txt"), "5.0 depth/0.000000.png\n").unwrap();
        let e = TumSequence::open(&seq).unwrap_err().to_string();
        assert!(e.contains("no colour frame has a depth frame"), "{e}");
        std::fs::write(seq.join("depth.txt"), "x depth/0.000000.png\n").unwrap();
        let e = TumSequence::open(&seq).unwrap_err().to_string();
        assert!(
            e.contains("depth.txt") && e.contains("timestamp `x`"),
            "{e}"
        );
        let e = TumSequence::open(&dir.path().join("missing"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("TUM RGB-D sequence"), "{e}");
    }
}
