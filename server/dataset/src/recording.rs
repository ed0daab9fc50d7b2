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
}

enum Source {
    Tum(TumSequence),
    Bag(Box<Bag>),
}

/// An opened recording: frames in time order, each with its stamp, pose (when known) and images.
pub struct Recording {
    /// The folder or file.
    pub path: PathBuf,
    source: Source,
    trajectory: Option<Trajectory>,
    depth_units_per_m: Option<f64>,
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
        Ok(Self {
            path: path.to_path_buf(),
            source,
            trajectory,
            depth_units_per_m: opts.depth_units_per_m,
        })
    }

    /// Frames (colour paired with depth).
    pub fn len(&self) -> usize {
        match &self.source {
            Source::Tum(s) => s.frames.len(),
            Source::Bag(b) => b.len(),
        }
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
            Source::Bag(b) => b.camera_problem.clone(),
        }
    }

    /// Why some frames have no pose (a bag's first failed TF or pose look-up), when some have none.
    pub fn pose_problem(&self) -> Option<String> {
        match &self.source {
            Source::Tum(_) => None,
            Source::Bag(b) => b.pose_problem.clone(),
        }
    }

    /// What the reader had to work around (a bag cut short, header stamps all zero).
    pub fn warnings(&self) -> Vec<String> {
        match &self.source {
            Source::Tum(_) => Vec::new(),
            Source::Bag(b) => b.warnings.clone(),
        }
    }

    /// Stamp of frame `i`, seconds.
    pub fn timestamp(&self, i: usize) -> f64 {
        match &self.source {
            Source::Tum(s) => s.frames[i].timestamp,
            Source::Bag(b) => b.timestamp(i),
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
        }
    }

    /// Decode frame `i`: colour, and depth in metres (0 = missing). Errors name the file.
    pub fn load(&self, i: usize) -> Result<(RgbImage, DepthMap), DatasetError> {
        match &self.source {
            Source::Tum(s) => s.load(i),
            Source::Bag(b) => b.load(i),
        }
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
