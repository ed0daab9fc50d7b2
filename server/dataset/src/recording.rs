//! A robot's recording, whatever its container: a TUM RGB-D folder or a ROS 2 bag, with the poses
//! its own file gives or those of a separate trajectory (the output of the user's SLAM), and the
//! overrides a user gives when the recording says something wrong (depth units).
//!
//! Every pose that comes out is `world_from_camera` with the optical camera axes (x right, y down, z
//! forward), the convention of TUM files and ROS camera frames.

use std::path::{Path, PathBuf};

use nalgebra::Isometry3;
use pntr_core::{DepthMap, Intrinsics, RgbImage};

use crate::bag::{Bag, Topics};
use crate::depth_camera::{register_depth, DepthCamera};
use crate::sevenscenes::{is_seven_scenes, SevenScenes};
use crate::tum::{Trajectory, TumSequence};
use crate::DatasetError;

/// How to read a recording.
#[derive(Debug, Clone, Default)]
pub struct RecordingOptions {
    /// Topics of a bag (ignored for a TUM folder).
    pub topics: Topics,
    /// A TUM trajectory file whose poses replace the recording's own (looked up at each frame's
    /// stamp, interpolated between samples).
    pub trajectory: Option<PathBuf>,
    /// Units per metre of integer depth, replacing what the format says (TUM 5000, ROS 16UC1 1000).
    pub depth_units_per_m: Option<f64>,
    /// The depth camera's `fx, fy, cx, cy` when the depth images are not registered to colour (its
    /// image size is the depth images'); a 7-Scenes folder's `camera-intrinsics.txt` when not given.
    pub depth_intrinsics: Option<[f64; 4]>,
    /// The depth camera's offset: a point in its optical frame to the colour camera's (identity when
    /// only `depth_intrinsics` is given).
    pub colour_from_depth: Option<Isometry3<f64>>,
}

enum Source {
    Tum(TumSequence),
    Bag(Box<Bag>),
    SevenScenes(SevenScenes),
}

/// An opened recording: frames in time order, each with its stamp, pose (when known) and images.
pub struct Recording {
    /// The folder or file.
    pub path: PathBuf,
    source: Source,
    trajectory: Option<Trajectory>,
    depth_units_per_m: Option<f64>,
    /// A separate depth camera: `fx, fy, cx, cy` and `colour_from_depth`.
    depth_camera: Option<([f64; 4], Isometry3<f64>)>,
    /// The colour camera depth is registered to ([`Recording::set_colour_camera`]).
    colour: Option<Intrinsics>,
}

impl std::fmt::Debug for Recording {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("path", &self.path)
            .field("frames", &self.len())
            .finish()
    }
}

/// True when `path` is a ROS 2 bag: an `.mcap` or `.db3` file, or a rosbag2 folder (one with
/// `metadata.yaml`).
pub fn is_bag(path: &Path) -> bool {
    if path.is_file() {
        return path
            .extension()
            .is_some_and(|x| x.eq_ignore_ascii_case("mcap") || x.eq_ignore_ascii_case("db3"));
    }
    path.is_dir() && path.join("metadata.yaml").is_file()
}

impl Recording {
    /// Open a TUM folder or a bag file. Errors name the file: what the readers refuse, a
    /// `--trajectory` file that does not parse, a depth unit that is not a positive number.
    pub fn open(path: &Path, opts: &RecordingOptions) -> Result<Self, DatasetError> {
        if let Some(u) = opts.depth_units_per_m {
            if !(u.is_finite() && u > 0.0) {
                return Err(DatasetError::Layout {
                    path: path.to_path_buf(),
                    problem: format!("depth units per metre must be a positive number, not {u}"),
                });
            }
        }
        let source = if is_bag(path) {
            let mut b = Bag::open(path, &opts.topics)?;
            if let Some(u) = opts.depth_units_per_m {
                b.depth_units_per_m = u;
            }
            Source::Bag(Box::new(b))
        } else if !path.join("rgb.txt").is_file() && is_seven_scenes(path) {
            let mut s = SevenScenes::open(path)?;
            if let Some(u) = opts.depth_units_per_m {
                s.depth_units_per_m = u;
            }
            Source::SevenScenes(s)
        } else {
            let mut s = TumSequence::open(path)?;
            if let Some(u) = opts.depth_units_per_m {
                s.depth_units_per_m = u;
            }
            Source::Tum(s)
        };
        let trajectory = match opts.trajectory.as_deref() {
            Some(t) if !t.is_file() => {
                return Err(DatasetError::Layout {
                    path: t.to_path_buf(),
                    problem: "the --trajectory file does not exist".into(),
                })
            }
            Some(t) => Some(Trajectory::read(t)?),
            None => None,
        };
        let own_depth_k = match &source {
            Source::SevenScenes(s) => s.intrinsics.map(|k| [k.fx, k.fy, k.cx, k.cy]),
            _ => None,
        };
        let depth_k = opts.depth_intrinsics.or(own_depth_k);
        if let Some(k) = opts.depth_intrinsics {
            if !k.iter().all(|x| x.is_finite()) || k[0] <= 0.0 || k[1] <= 0.0 {
                return Err(DatasetError::Layout {
                    path: path.to_path_buf(),
                    problem: format!("the depth camera's intrinsics must be finite with positive focal lengths, not {k:?}"),
                });
            }
        }
        if opts.colour_from_depth.is_some() && depth_k.is_none() {
            // A 7-Scenes folder names its depth camera in camera-intrinsics.txt: say it is missing.
            let file = if matches!(source, Source::SevenScenes(_)) {
                ", or copy the recording's camera-intrinsics.txt into this folder"
            } else {
                ""
            };
            return Err(DatasetError::Layout {
                path: path.to_path_buf(),
                problem: format!("a depth-to-colour offset needs the depth camera's intrinsics too (--depth-intrinsics fx,fy,cx,cy{file})"),
            });
        }
        let depth_camera = depth_k.map(|k| {
            (
                k,
                opts.colour_from_depth.unwrap_or_else(Isometry3::identity),
            )
        });
        Ok(Self {
            path: path.to_path_buf(),
            source,
            trajectory,
            depth_units_per_m: opts.depth_units_per_m,
            depth_camera,
            colour: None,
        })
    }

    /// Frames (colour paired with depth).
    pub fn len(&self) -> usize {
        match &self.source {
            Source::Tum(s) => s.frames.len(),
            Source::Bag(b) => b.len(),
            Source::SevenScenes(s) => s.frames.len(),
        }
    }

    /// Whether depth comes from a separate depth camera that [`Recording::load`] registers to the
    /// colour camera ([`crate::depth_camera`]).
    pub fn has_depth_camera(&self) -> bool {
        self.depth_camera.is_some()
    }

    /// The colour camera that frames' depth is registered to (the recording's own or the user's):
    /// needed before [`Recording::load`] when [`Recording::has_depth_camera`].
    pub fn set_colour_camera(&mut self, colour: Intrinsics) {
        self.colour = Some(colour);
    }

    /// True without frames.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The camera the recording names (calibration.txt, CameraInfo), if any.
    pub fn intrinsics(&self) -> Option<Intrinsics> {
        match &self.source {
            Source::Tum(s) => s.intrinsics,
            Source::Bag(b) => b.intrinsics,
            // camera-intrinsics.txt is the depth camera's (the poses' and depth's), not colour's.
            Source::SevenScenes(_) => None,
        }
    }

    /// The depth unit the caller gave (`--depth-scale`), if any.
    pub fn depth_units_per_m(&self) -> Option<f64> {
        self.depth_units_per_m
    }

    /// Why the recording's own camera cannot be used, when it cannot (a bag's CameraInfo with an
    /// unknown distortion model or an all-zero K): give the camera yourself.
    pub fn camera_problem(&self) -> Option<String> {
        match &self.source {
            Source::Tum(_) => None,
            Source::SevenScenes(_) => Some("a 7-Scenes folder names only its depth camera (camera-intrinsics.txt), not the colour camera (7-Scenes' Kinect: 525,525,320,240)".into()),
            Source::Bag(b) => b.camera_problem.clone(),
        }
    }

    /// Why some frames have no pose (a bag's first failed TF or pose look-up), when some have none.
    pub fn pose_problem(&self) -> Option<String> {
        match &self.source {
            Source::Tum(_) | Source::SevenScenes(_) => None,
            Source::Bag(b) => b.pose_problem.clone(),
        }
    }

    /// What the reader had to work around (a bag cut short, header stamps all zero).
    pub fn warnings(&self) -> Vec<String> {
        match &self.source {
            Source::Tum(_) => Vec::new(),
            Source::SevenScenes(_) if self.depth_camera.is_some_and(|(_, e)| e == Isometry3::identity()) => vec![
                "the depth camera's offset to the colour camera is not given (--depth-to-colour): depth is registered with the two cameras' intrinsics alone; 7-Scenes' Kinect: --depth-to-colour -0.0256,0.0001,0.0020".into(),
            ],
            Source::SevenScenes(_) => Vec::new(),
            Source::Bag(b) => b.warnings.clone(),
        }
    }

    /// Stamp of frame `i`, seconds.
    pub fn timestamp(&self, i: usize) -> f64 {
        match &self.source {
            Source::Tum(s) => s.frames[i].timestamp,
            Source::Bag(b) => b.timestamp(i),
            Source::SevenScenes(s) => s.timestamp(i),
        }
    }

    /// `world_from_camera` of frame `i` (optical axes): from the trajectory file when one was given,
    /// else the recording's own (groundtruth.txt, a pose topic); `None` when neither has it.
    pub fn world_from_camera(&self, i: usize) -> Option<Isometry3<f64>> {
        if let Some(t) = &self.trajectory {
            return t.at(self.timestamp(i));
        }
        match &self.source {
            Source::Tum(s) => s.frames[i].world_from_camera,
            Source::Bag(b) => b.ground_truth(i),
            // The layout's poses are the depth camera's: the colour camera's is one offset away.
            Source::SevenScenes(s) => {
                s.frames[i]
                    .world_from_camera
                    .map(|w| match &self.depth_camera {
                        Some((_, colour_from_depth)) => w * colour_from_depth.inverse(),
                        None => w,
                    })
            }
        }
    }

    /// Decode frame `i`: colour, and depth in metres (0 = missing), registered to the colour image
    /// when the depth comes from a separate depth camera. Errors name the file; with a depth camera,
    /// also when the colour camera was not set ([`Recording::set_colour_camera`]) or the depth image
    /// does not have the depth camera's size.
    pub fn load(&self, i: usize) -> Result<(RgbImage, DepthMap), DatasetError> {
        let (rgb, depth) = self.load_as_recorded(i)?;
        let Some((k, colour_from_depth)) = self.depth_camera else {
            return Ok((rgb, depth));
        };
        let problem = |p: String| DatasetError::Layout {
            path: self.path.clone(),
            problem: format!("frame {i}: {p}"),
        };
        let colour = self.colour.ok_or_else(|| {
            problem("depth from a separate depth camera needs the colour camera (--intrinsics) to be registered to".into())
        })?;
        if (colour.width, colour.height) != (rgb.width, rgb.height) {
            return Err(problem(format!(
                "the colour image is {}x{} but the colour camera is {}x{}",
                rgb.width, rgb.height, colour.width, colour.height
            )));
        }
        let camera = DepthCamera {
            intrinsics: Intrinsics {
                fx: k[0],
                fy: k[1],
                cx: k[2],
                cy: k[3],
                width: depth.width,
                height: depth.height,
                distortion: [0.0; 5],
            },
            colour_from_depth,
        };
        let depth = register_depth(&depth, &camera, &colour).map_err(problem)?;
        Ok((rgb, depth))
    }

    /// Frame `i` as the recording holds it: depth in the depth camera's pixels when it has one.
    fn load_as_recorded(&self, i: usize) -> Result<(RgbImage, DepthMap), DatasetError> {
        match &self.source {
            Source::Tum(s) => s.load(i),
            Source::Bag(b) => b.load(i),
            Source::SevenScenes(s) => s.load(i),
        }
    }

    /// The colour image's size of the first readable frame among the first 50.
    pub fn image_size(&self) -> Option<(u32, u32)> {
        (0..self.len().min(50)).find_map(|i| {
            let (rgb, _) = self.load_as_recorded(i).ok()?;
            Some((rgb.width, rgb.height))
        })
    }

    /// A short name for ids and reports: the folder's or file's name without extension.
    pub fn name(&self) -> String {
        self.path
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_else(|| "recording".into())
    }
}

/// What the depth of a frame says about its unit: `Some(message)` when the median valid depth is
/// outside what an indoor RGB-D camera sees (0.15-15 m), naming the likely mistake.
pub fn depth_unit_hint(depth: &DepthMap, units_per_m: Option<f64>) -> Option<String> {
    let mut v: Vec<f32> = depth
        .data
        .iter()
        .copied()
        .filter(|d| d.is_finite() && *d > 0.0)
        .collect();
    if v.len() < 16 {
        return None;
    }
    v.sort_unstable_by(f32::total_cmp);
    let m = v[v.len() / 2] as f64;
    let p95 = v[v.len() * 95 / 100] as f64;
    let said = units_per_m.map_or("the format's".to_string(), |u| {
        format!("{u} (your --depth-scale)")
    });
    // The units that would put the median at a typical indoor 2.5 m, rounded to a common one.
    let now = units_per_m.unwrap_or(1000.0);
    let guess = [1.0, 10.0, 100.0, 1000.0, 4000.0, 5000.0, 10000.0]
        .into_iter()
        .min_by(|a, b| {
            let want = now * m / 2.5;
            (a / want).ln().abs().total_cmp(&(b / want).ln().abs())
        })
        .unwrap_or(1000.0);
    if m > 15.0 || p95 > 25.0 {
        Some(format!(
            "the median depth is {m:.1} m and 5% of pixels are beyond {p95:.1} m at {said} units per metre: farther than an indoor RGB-D camera measures; the depth is likely in finer units (give --depth-scale with the sensor's units per metre: {guess} fits this frame; 1000 for millimetres, 4000 for 0.25 mm, 5000 for TUM's)"
        ))
    } else if m < 0.15 {
        Some(format!(
            "the median depth is {m:.3} m at {said} units per metre: too near for an indoor RGB-D camera; the depth is likely in coarser units (give --depth-scale with the sensor's units per metre: {guess} fits this frame; 1 for metres, 100 for centimetres)"
        ))
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_seven_scenes_folder_without_its_depth_camera_names_the_missing_file() {
        // A query folder made of the frames alone: the offset is given, camera-intrinsics.txt is
        // not there (a new user copied the frames only).
        let dir = tempfile::tempdir().unwrap();
        for (name, text) in [
            ("frame-000250.color.png", ""),
            ("frame-000250.depth.png", ""),
            (
                "frame-000250.pose.txt",
                "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n",
            ),
        ] {
            std::fs::write(dir.path().join(name), text).unwrap();
        }
        let opts = RecordingOptions {
            colour_from_depth: Some(Isometry3::identity()),
            ..Default::default()
        };
        let e = Recording::open(dir.path(), &opts)
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("--depth-intrinsics") && e.contains("camera-intrinsics.txt"),
            "{e}"
        );
    }

    #[test]
    fn a_depth_in_the_wrong_unit_is_named() {
        let at = |m: f32| DepthMap {
            width: 8,
            height: 4,
            data: vec![m; 32],
        };
        assert!(depth_unit_hint(&at(2.5), None).is_none());
        let far = depth_unit_hint(&at(40.0), Some(1000.0)).unwrap();
        assert!(
            far.contains("finer units") && far.contains("--depth-scale"),
            "{far}"
        );
        let near = depth_unit_hint(&at(0.05), None).unwrap();
        assert!(near.contains("coarser units"), "{near}");
        // Metres in a 16-bit PNG read as millimetres: 2 m reads 0.002 m; the fix is 1 unit a metre.
        let metres = depth_unit_hint(&at(0.002), Some(1000.0)).unwrap();
        assert!(metres.contains("1 fits this frame"), "{metres}");
        // TUM's 5000 a metre read as millimetres: a median of 7 m passes, the far tail does not.
        let mut tum = at(1.4 * 5.0);
        for d in tum.data.iter_mut().take(4) {
            *d = 6.0 * 5.0;
        }
        let far_tail = depth_unit_hint(&tum, Some(1000.0)).unwrap();
        assert!(
            far_tail.contains("finer units") && far_tail.contains("5000 for TUM"),
            "{far_tail}"
        );
    }
}
