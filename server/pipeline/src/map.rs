//! The map: every database image with what localisation needs, and the retrieval stage over them.
//!
//! Built by `pntr-mapping` (from HPointLoc-layout Point files or recordings): per database image its pose, keypoints,
//! local descriptors (float ones stored as f16, which halves the largest part of the map for a
//! relative error near 1e-3; binary ORB ones as they are), the 3D point of every keypoint in the
//! camera's OpenCV frame from the image's own depth (NaN where the depth is invalid: the keypoint stays
//! in place, so indices never shift and pairs never misalign), and the instance id under it.

use std::path::PathBuf;

use half::f16;
use nalgebra::{Isometry3, Vector3};
use pntr_core::{DepthMap, Intrinsics, LabelMap};
use pntr_features::Features;
use pntr_retrieval::global::{Describer, Retriever};
use serde::{Deserialize, Serialize};

use crate::preset::Preset;
use crate::verify::Thumb;

/// One database image of the map.
#[derive(Debug, Clone, PartialEq)]
pub struct MapImage {
    /// Stable id: `<scene>/point<N>/db<i>`.
    pub id: String,
    /// Index into [`MapHeader::scenes`].
    pub scene: u32,
    /// The Point (key position) it was taken at.
    pub point: u32,
    /// Camera-to-world pose in the map's world frame, with the map's camera axes
    /// ([`MapHeader::camera_axes`]: Habitat for HPointLoc data, OpenCV's optical axes for recordings).
    pub world_from_camera: Isometry3<f64>,
    /// The recording's stamp of the frame, seconds (`None` for dataset views).
    pub stamp: Option<f64>,
    /// Keypoints (x, y) in pixels, OpenCV convention.
    pub keypoints: Vec<[f32; 2]>,
    /// Detection scores.
    pub scores: Vec<f32>,
    /// Float descriptors as f16, `keypoints.len() * dim` (empty for binary extractors).
    pub descriptors: Vec<f16>,
    /// Float descriptor length.
    pub dim: usize,
    /// Binary descriptors (ORB).
    pub binary: Vec<[u8; 32]>,
    /// 3D point of each keypoint in the camera's OpenCV frame (metres); NaN where depth is invalid.
    pub points: Vec<[f32; 3]>,
    /// Instance id under each keypoint (0 where the dataset has no labels).
    pub instances: Vec<u32>,
    /// (width, height) of the image.
    pub image_size: (u32, u32),
    /// The camera that took it (its keypoints and points are in its pixels and frame).
    pub camera: Intrinsics,
    /// Reduced depth and grey for verification ([`crate::verify::Thumb`], about 12 KiB).
    pub thumb: Thumb,
    /// Finer depth for the dense refinement ([`crate::refine::fine_depth`]): cameras of focal
    /// length 256 px and more (160 x 120 samples, about 56 KiB, for a VGA camera); `None` for
    /// smaller ones and in maps of format 4 and older, whose refinement aligns [`Self::thumb`].
    pub fine: Option<Thumb>,
}

impl MapImage {
    /// The features in the form the matchers take (f16 widened to f32).
    pub fn features(&self) -> Features {
        let mut f = Features::default();
        self.features_into(&mut f);
        f
    }

    /// [`Self::features`] written into `out`, reusing its buffers (a query matched against image
    /// after image allocates nothing after the first).
    pub fn features_into(&self, out: &mut Features) {
        use half::slice::HalfFloatSliceExt;
        out.keypoints.clear();
        out.keypoints.extend_from_slice(&self.keypoints);
        out.scores.clear();
        out.scores.extend_from_slice(&self.scores);
        out.descriptors.clear();
        out.descriptors.resize(self.descriptors.len(), 0.0);
        self.descriptors.convert_to_f32_slice(&mut out.descriptors);
        out.dim = self.dim;
        out.binary.clear();
        out.binary.extend_from_slice(&self.binary);
        out.image_size = self.image_size;
    }

    /// The 3D point of keypoint `i`, where its depth was valid.
    pub fn point(&self, i: usize) -> Option<Vector3<f64>> {
        let p = self.points.get(i)?;
        p[0].is_finite()
            .then(|| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64))
    }

    /// Bytes this image holds in memory (approximately).
    pub fn heap_bytes(&self) -> usize {
        self.id.len()
            + self.keypoints.len() * (8 + 4 + 12 + 4)
            + self.descriptors.len() * 2
            + self.binary.len() * 32
            + self.thumb.heap_bytes()
            + self.fine.as_ref().map_or(0, Thumb::heap_bytes)
    }
}

/// Identity of a model the map depends on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModelIdentity {
    /// Role: `extractor` (what described the map's images), `query_extractor` (what describes the
    /// queries, when the preset uses another backbone for them: `xfeat-mnn-int8`, `xfeat-mnn-bf16`), `matcher` or
    /// `global`.
    pub role: String,
    /// The configured name (xfeat, lighterglue, ...).
    pub name: String,
    /// File name of the model, when there is one.
    pub file: Option<String>,
    /// FNV-1a checksum of the model file, when there is one.
    pub checksum: Option<String>,
}

/// Check a map id chosen by a user (`build-db --map-id`): 1 to 128 characters of `A-Z a-z 0-9 . _ -`,
/// so that it travels unchanged in requests, gRPC metadata (`x-pntr-map-id`), Prometheus labels and
/// file names. The error says what is wrong.
pub fn check_map_id(id: &str) -> Result<(), String> {
    if id.is_empty() || id.len() > 128 {
        return Err(format!(
            "map id {id:?}: give 1 to 128 characters (letters, digits, '.', '_', '-')"
        ));
    }
    if let Some(c) = id
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')))
    {
        return Err(format!(
            "map id {id:?}: {c:?} is not allowed (letters, digits, '.', '_', '-' only: the id travels in gRPC metadata and metric labels)"
        ));
    }
    Ok(())
}

/// What a map file says about itself (stored as JSON in the header section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapHeader {
    /// Map id clients name in requests (the scene name, or `all` for a multi-scene map).
    pub map_id: String,
    /// The preset the map was built with.
    pub preset: Preset,
    /// Models whose output is stored in the map.
    pub models: Vec<ModelIdentity>,
    /// Camera of the first database image; each image records its own ([`MapImage::camera`]).
    pub intrinsics: Intrinsics,
    /// Camera axes of stored poses and of every pose given out for this map: `habitat` (x right, y
    /// up, looking along -z) for HPointLoc data and `pntr synth` datasets, `opencv` (the optical axes
    /// of TUM and ROS: x right, y down, z forward) for maps built from recordings.
    pub camera_axes: String,
    /// The world's up axis: `y` (HPointLoc, `pntr synth`) or `z` (REP 103 frames such as a ROS
    /// `map`). Maps written before it was recorded are y-up.
    #[serde(default = "default_up_axis")]
    pub up_axis: String,
    /// Scenes in the map; each has its own world frame.
    pub scenes: Vec<String>,
    /// The pntr version that built it.
    pub built_by: String,
    /// Seconds the build took.
    pub build_seconds: f64,
    /// When the map was built (or last extended), seconds since the Unix epoch, UTC. Maps written
    /// before it was recorded have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub built_at_unix_s: Option<f64>,
    /// The recordings the map was built or extended from, in order (empty for a dataset's map).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sessions: Vec<SessionRecord>,
    /// The map's own confidence calibration, fitted on its frames with each region held out
    /// (`pntr_mapping::selfcal`); `None` for a map built without it (the shipped calibration then
    /// applies). Checked when the map is read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::calibration::MapCalibration>,
}

/// One recording a map was built or extended from: what tells it again.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SessionRecord {
    /// The recording's name (its folder or file name).
    pub name: String,
    /// Frames it has.
    pub frames: usize,
    /// Stamps of its first and last frames, seconds.
    pub first_stamp: f64,
    /// See `first_stamp`.
    pub last_stamp: f64,
}

/// The up axis of maps written before [`MapHeader::up_axis`] was recorded: `y`.
pub fn default_up_axis() -> String {
    "y".into()
}

impl MapHeader {
    /// The camera axes of the map's poses ([`MapHeader::camera_axes`]); an unknown name is read as
    /// Habitat's, what every map had before the field could say otherwise.
    pub fn axes(&self) -> pntr_core::CameraAxes {
        pntr_core::CameraAxes::parse(&self.camera_axes).unwrap_or(pntr_core::CameraAxes::Habitat)
    }

    /// The world's up direction as a unit vector (`+y` unless [`MapHeader::up_axis`] is `z`).
    pub fn up(&self) -> Vector3<f64> {
        if self.up_axis.eq_ignore_ascii_case("z") {
            Vector3::z()
        } else {
            Vector3::y()
        }
    }
}

/// A loaded or freshly built map.
#[derive(Debug)]
pub struct Map {
    /// The header.
    pub header: MapHeader,
    /// Database images, in retrieval-id order.
    pub images: Vec<MapImage>,
    /// Retrieval over the images.
    pub retriever: Retriever,
    /// FNV-1a over the checksums of the file's sections (HEAD, IMGS, RETR) when the map was read
    /// from a file, so two files with the same content have the same value; 0 for a map built in
    /// memory and not read back.
    pub checksum: u64,
}

impl Map {
    /// [`crate::calibration::image_fingerprint`] of this map's images.
    pub fn image_fingerprint(&self) -> String {
        crate::calibration::image_fingerprint(self.images.iter().map(|im| im.id.as_str()))
    }

    /// True when the map carries its own calibration but was extended or merged since it was
    /// fitted (other images than it was fitted for).
    pub fn calibration_is_stale(&self) -> bool {
        self.header
            .calibration
            .as_ref()
            .is_some_and(|c| c.is_stale_for(self.images.iter().map(|im| im.id.as_str())))
    }

    /// Bytes the map holds in memory, approximately (images plus retrieval vectors).
    pub fn heap_bytes(&self) -> usize {
        let dense = match &self.retriever.describer {
            Describer::Vlad(b) => b.vlad_dim() * 4,
            Describer::Onnx(m) => m.dim() * 4,
            Describer::Bow(_) => 0,
        };
        self.images
            .iter()
            .map(|i| i.heap_bytes() + dense)
            .sum::<usize>()
    }

    /// The focal length queries are resampled to, pixels: the median over the images' cameras of
    /// `sqrt(fx * fy)` (the header's camera for an empty map).
    pub fn focal_px(&self) -> f64 {
        let mut f: Vec<f64> = self
            .images
            .iter()
            .map(|im| (im.camera.fx * im.camera.fy).sqrt())
            .collect();
        if f.is_empty() {
            return (self.header.intrinsics.fx * self.header.intrinsics.fy).sqrt();
        }
        f.sort_by(f64::total_cmp);
        f[f.len() / 2]
    }

    /// Pixels of a map image (the median over the images' cameras; HPointLoc's 256x256 for an empty
    /// map): what a query's coverage is compared with.
    pub fn image_pixels(&self) -> f64 {
        let mut px: Vec<f64> = self
            .images
            .iter()
            .map(|im| im.camera.width as f64 * im.camera.height as f64)
            .collect();
        px.sort_by(f64::total_cmp);
        px.get(px.len() / 2).copied().unwrap_or(65536.0)
    }

    /// Name of the scene of image `i`.
    pub fn scene_of(&self, i: usize) -> &str {
        self.header
            .scenes
            .get(self.images[i].scene as usize)
            .map(String::as_str)
            .unwrap_or("")
    }
}

/// Seconds since the Unix epoch now (0 on a clock set before 1970).
pub fn unix_now_s() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Back-project every keypoint with the image's depth (NaN where invalid) and read its instance id.
pub fn keypoint_points(
    k: &Intrinsics,
    depth: &DepthMap,
    labels: Option<&LabelMap>,
    keypoints: &[[f32; 2]],
) -> (Vec<[f32; 3]>, Vec<u32>) {
    let mut pts = Vec::with_capacity(keypoints.len());
    let mut ids = Vec::with_capacity(keypoints.len());
    for kp in keypoints {
        let (c, r) = (kp[0].round(), kp[1].round());
        let inside = c >= 0.0 && r >= 0.0 && (c as u32) < depth.width && (r as u32) < depth.height;
        let z = inside
            .then(|| depth.get(c as u32, r as u32))
            .flatten()
            .filter(|z| z.is_finite());
        pts.push(match z {
            Some(z) => {
                let p = k.backproject(kp[0] as f64, kp[1] as f64, z as f64);
                [p.x as f32, p.y as f32, p.z as f32]
            }
            None => [f32::NAN; 3],
        });
        ids.push(match labels {
            Some(l) if inside && c < l.width as f32 && r < l.height as f32 => {
                l.get(c as u32, r as u32)
            }
            _ => 0,
        });
    }
    (pts, ids)
}

/// Where a map built from a dataset is cached: `<dir>/<map_id>-<preset>.pntrmap`.
pub fn cache_path(dir: &std::path::Path, map_id: &str, preset: &str) -> PathBuf {
    dir.join(format!("{map_id}-{preset}.pntrmap"))
}
