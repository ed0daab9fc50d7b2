//! Recordings and cameras as the commands take them: `--sequence` (a TUM folder, a 7-Scenes
//! folder, a ROS 2 bag or MCAP file) with its bag topics ([`TopicArgs`]), `--trajectory`,
//! `--depth-scale` and `--intrinsics`.

use std::path::Path;

use anyhow::{bail, Context, Result};
use nalgebra::Isometry3;
use pntr_core::Intrinsics;
use pntr_dataset::bag::Topics;
use pntr_dataset::recording::{Recording, RecordingOptions};
use pntr_mapping::recording_map::Session;
use pntr_service::proto;

/// A separate depth camera's `fx, fy, cx, cy` and `colour_from_depth`, each when given.
pub type DepthCameraOptions = (Option<[f64; 4]>, Option<Isometry3<f64>>);

/// The topics of a ROS 2 bag (`pntr replay`, `pntr build-db --sequence`).
#[derive(clap::Args, Debug, Clone)]
pub struct TopicArgs {
    /// ROS 2 bag: the colour topic (sensor_msgs/Image, rgb8/bgr8/rgba8/bgra8; when absent, its
    /// `/compressed` sibling, sensor_msgs/CompressedImage JPEG or PNG).
    #[arg(long, default_value = "/camera/color/image_raw")]
    pub rgb_topic: String,
    /// ROS 2 bag: the depth topic, aligned to the colour camera (16UC1 millimetres or 32FC1 metres;
    /// when absent, its `/compressedDepth` sibling).
    #[arg(long, default_value = "/camera/aligned_depth_to_color/image_raw")]
    pub depth_topic: String,
    /// ROS 2 bag: the colour camera's sensor_msgs/CameraInfo topic.
    #[arg(long, default_value = "/camera/color/camera_info")]
    pub info_topic: String,
    /// ROS 2 bag: poses from this topic instead of TF: geometry_msgs/PoseStamped (world_from_camera
    /// of the optical frame) or nav_msgs/Odometry (of the body; the camera's offset from TF).
    #[arg(long)]
    pub pose_topic: Option<String>,
    /// ROS 2 bag: the world frame of TF poses.
    #[arg(long, default_value = "map")]
    pub map_frame: String,
    /// ROS 2 bag: the camera's optical frame in TF (default: the colour images' frame_id).
    #[arg(long)]
    pub camera_frame: Option<String>,
    /// A separate depth camera (`--depth-intrinsics`, `--depth-to-colour`).
    #[command(flatten)]
    pub depth: DepthCameraArgs,
}

/// Depth from a separate depth camera, registered to the colour image by pntr (`pntr replay`,
/// `pntr build-db --sequence`, `pntr localize`).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct DepthCameraArgs {
    /// Depth from a separate depth camera (not registered to colour): its `fx,fy,cx,cy` (its image
    /// size is the depth images'). pntr registers each depth image to the colour camera. A 7-Scenes
    /// folder's camera-intrinsics.txt (for single files, the one beside the depth file) is taken
    /// when this is not given.
    #[arg(long, value_name = "FX,FY,CX,CY")]
    pub depth_intrinsics: Option<String>,
    /// The depth camera's offset: `tx,ty,tz[,qx,qy,qz,qw]` (metres; quaternion x, y, z, w) taking a
    /// point in the depth camera's optical frame to the colour camera's (a calibration's "depth to
    /// colour" extrinsics; 7-Scenes' Kinect: -0.0256,0.0001,0.0020).
    #[arg(
        long,
        value_name = "TX,TY,TZ[,QX,QY,QZ,QW]",
        allow_hyphen_values = true
    )]
    pub depth_to_colour: Option<String>,
}

impl DepthCameraArgs {
    /// The reader's options for a separate depth camera: `--depth-intrinsics` and
    /// `--depth-to-colour`, parsed.
    pub fn depth_camera(&self) -> Result<DepthCameraOptions> {
        let numbers = |flag: &str, s: &str| -> Result<Vec<f64>> {
            s.split([',', ' '])
                .filter(|w| !w.is_empty())
                .map(|w| {
                    w.parse::<f64>()
                        .ok()
                        .filter(|x| x.is_finite())
                        .with_context(|| format!("{flag}: `{w}` is not a number"))
                })
                .collect()
        };
        let k = match self.depth_intrinsics.as_deref() {
            None => None,
            Some(s) => match numbers("--depth-intrinsics", s)?[..] {
                [fx, fy, cx, cy] if fx > 0.0 && fy > 0.0 => Some([fx, fy, cx, cy]),
                _ => bail!(
                    "--depth-intrinsics {s}: give fx,fy,cx,cy (pixels, positive focal lengths)"
                ),
            },
        };
        let e = match self.depth_to_colour.as_deref() {
            None => None,
            Some(s) => {
                let v = numbers("--depth-to-colour", s)?;
                let t = nalgebra::Translation3::new(
                    *v.first().unwrap_or(&0.0),
                    *v.get(1).unwrap_or(&0.0),
                    *v.get(2).unwrap_or(&0.0),
                );
                let q = match v.len() {
                    3 => nalgebra::UnitQuaternion::identity(),
                    7 => {
                        let q = nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]);
                        let n = q.norm();
                        if (n - 1.0).abs() > 1e-3 {
                            bail!("--depth-to-colour {s}: the quaternion's norm is {n:.4}, not 1");
                        }
                        nalgebra::UnitQuaternion::from_quaternion(q)
                    }
                    _ => bail!("--depth-to-colour {s}: give tx,ty,tz or tx,ty,tz,qx,qy,qz,qw"),
                };
                if t.vector.norm() > 0.5 {
                    bail!("--depth-to-colour {s}: the cameras would be {:.2} m apart; the offset is in metres (2.56 cm is 0.0256)", t.vector.norm());
                }
                Some(Isometry3::from_parts(t, q))
            }
        };
        Ok((k, e))
    }
}

impl TopicArgs {
    /// [`DepthCameraArgs::depth_camera`] of these arguments.
    pub fn depth_camera(&self) -> Result<DepthCameraOptions> {
        self.depth.depth_camera()
    }

    /// The reader's topics.
    pub fn topics(&self) -> Topics {
        Topics {
            rgb: self.rgb_topic.clone(),
            depth: self.depth_topic.clone(),
            info: self.info_topic.clone(),
            pose: self.pose_topic.clone(),
            map_frame: self.map_frame.clone(),
            camera_frame: self.camera_frame.clone(),
        }
    }
}

/// Parse `--intrinsics`: 4 numbers (fx, fy, cx, cy), 8 (with k1, k2, p1, p2) or 9 (with k3),
/// separated by commas and/or spaces.
pub fn parse_intrinsics(words: &[String]) -> Result<proto::Intrinsics> {
    let mut v = Vec::new();
    for w in words {
        for item in w.split([',', ' ']).filter(|s| !s.is_empty()) {
            let x: f64 = item.parse().with_context(|| {
                format!("--intrinsics: `{item}` is not a number (expected fx,fy,cx,cy[,k1,k2,p1,p2,k3])")
            })?;
            if !x.is_finite() {
                bail!("--intrinsics: `{item}` is not finite");
            }
            v.push(x);
        }
    }
    if !matches!(v.len(), 4 | 8 | 9) {
        bail!(
            "--intrinsics takes fx,fy,cx,cy or fx,fy,cx,cy,k1,k2,p1,p2[,k3] (4, 8 or 9 numbers), got {}",
            v.len()
        );
    }
    if v[0] <= 0.0 || v[1] <= 0.0 {
        bail!(
            "--intrinsics: focal lengths fx = {} and fy = {} must be positive",
            v[0],
            v[1]
        );
    }
    Ok(proto::Intrinsics {
        fx: v[0],
        fy: v[1],
        cx: v[2],
        cy: v[3],
        distortion: v[4..].to_vec(),
    })
}

/// The camera of `rec`: `--intrinsics` (at the size of the recording's first readable frame) or
/// the recording's own calibration.
pub fn camera_of(rec: &Recording, intrinsics: Option<&str>) -> Result<Intrinsics> {
    let Some(text) = intrinsics else {
        return rec.intrinsics().with_context(|| {
            format!(
                "{}: {}; give the camera with --intrinsics fx,fy,cx,cy[,k1,k2,p1,p2,k3]",
                rec.path.display(),
                rec.camera_problem()
                    .unwrap_or_else(|| "no calibration.txt or camera info".into())
            )
        });
    };
    let m = parse_intrinsics(&[text.to_string()])?;
    let (width, height) = rec.image_size().with_context(|| {
        format!(
            "{}: none of the first frames could be read",
            rec.path.display()
        )
    })?;
    let mut k = Intrinsics {
        fx: m.fx,
        fy: m.fy,
        cx: m.cx,
        cy: m.cy,
        width,
        height,
        ..Intrinsics::hpointloc()
    };
    for (d, v) in k.distortion.iter_mut().zip(&m.distortion) {
        *d = *v;
    }
    k.validate()
        .map_err(|e| anyhow::anyhow!("--intrinsics {text}: {e}"))?;
    Ok(k)
}

/// Open recording `path` (`--sequence`) with its poses from `trajectory` when given, `topics` for a
/// bag, `depth_scale` units per metre and `intrinsics` (`fx,fy,cx,cy[,...]`) replacing what the
/// recording says; its camera.
pub fn open_recording(
    path: &Path,
    trajectory: Option<&Path>,
    topics: &TopicArgs,
    depth_scale: Option<f64>,
    intrinsics: Option<&str>,
) -> Result<(Recording, Intrinsics)> {
    let (depth_intrinsics, colour_from_depth) = topics.depth_camera()?;
    let opts = RecordingOptions {
        topics: topics.topics(),
        trajectory: trajectory.map(Path::to_path_buf),
        depth_units_per_m: depth_scale,
        depth_intrinsics,
        colour_from_depth,
    };
    let mut rec =
        Recording::open(path, &opts).with_context(|| format!("--sequence {}", path.display()))?;
    let camera = camera_of(&rec, intrinsics)?;
    rec.set_colour_camera(camera);
    Ok((rec, camera))
}

pub fn as_sessions(recs: &[(Recording, Intrinsics)]) -> Vec<Session<'_>> {
    recs.iter()
        .map(|(recording, camera)| Session {
            recording,
            camera: *camera,
        })
        .collect()
}
