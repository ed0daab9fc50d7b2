//! The map: every database image with what localisation needs, and the retrieval stage over them.
//!
//! Built once by [`build`] from HPointLoc-layout Point files: per database image its pose, keypoints,
//! local descriptors (float ones stored as f16, which halves the largest part of the map for a
//! relative error near 1e-3; binary ORB ones as they are), the 3D point of every keypoint in the
//! camera's OpenCV frame from the image's own depth (NaN where the depth is invalid: the keypoint stays
//! in place, so indices never shift and pairs never misalign), and the instance id under it.

use std::path::PathBuf;
use std::time::Instant;

use half::f16;
use nalgebra::{Isometry3, Vector3};
use pntr_core::{DepthMap, Intrinsics, LabelMap, RgbImage};
use pntr_dataset::{Role, SceneEntry};
use pntr_features::config::FeatureStage;
use pntr_features::Features;
use pntr_retrieval::global::{Describer, Descriptor, Method, Retriever};
use pntr_retrieval::onnx_global::OnnxGlobal;
use serde::{Deserialize, Serialize};

use crate::preset::Preset;
use crate::verify::Thumb;
use crate::PipelineError;

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
        Features {
            keypoints: self.keypoints.clone(),
            scores: self.scores.clone(),
            descriptors: self.descriptors.iter().map(|x| x.to_f32()).collect(),
            dim: self.dim,
            binary: self.binary.clone(),
            image_size: self.image_size,
        }
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
    /// ([`crate::selfcal`]); `None` for a map built without it (the shipped calibration then
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

fn default_up_axis() -> String {
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

/// FNV-1a checksum of a model file, as hex.
pub fn file_checksum(path: &std::path::Path) -> Result<String, PipelineError> {
    let bytes = std::fs::read(path).map_err(|e| PipelineError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    Ok(format!("{:016x}", pntr_core::bytes::fnv1a(&bytes)))
}

/// The model files a preset uses, by role and name. A missing file is an error naming it, so a map is
/// not built for a preset whose query model is absent.
pub fn model_identities(
    preset: &Preset,
    models_dir: &std::path::Path,
) -> Result<Vec<ModelIdentity>, PipelineError> {
    let file_of = pntr_features::config::model_file;
    let mut out = Vec::new();
    let mut roles = vec![("extractor", preset.map_extractor())];
    if preset.extractor != preset.map_extractor() {
        roles.push(("query_extractor", preset.extractor.as_str()));
    }
    roles.push(("matcher", preset.matcher.as_str()));
    for (role, name) in roles {
        let file = file_of(name);
        let checksum = match file {
            Some(f) => Some(file_checksum(&models_dir.join(f))?),
            None => None,
        };
        out.push(ModelIdentity {
            role: role.into(),
            name: name.to_string(),
            file: file.map(String::from),
            checksum,
        });
    }
    if let Some(p) = &preset.global_model {
        out.push(ModelIdentity {
            role: "global".into(),
            name: "onnx".into(),
            file: Some(p.display().to_string()),
            checksum: Some(file_checksum(p)?),
        });
    }
    Ok(out)
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

/// Local descriptors sampled for codebook training: at most this many in all.
const TRAINING_DESCRIPTORS: usize = 200_000;

/// A map under construction: images are added one at a time (features extracted as they come, so
/// the frames themselves are not kept), then [`MapBuilder::finish`] learns the retrieval stage on them.
pub struct MapBuilder<'a> {
    preset: &'a Preset,
    stage: &'a FeatureStage,
    global_model: Option<OnnxGlobal>,
    images: Vec<MapImage>,
    onnx_desc: Vec<Descriptor>,
    header_camera: Option<Intrinsics>,
    t0: Instant,
    /// The map being extended ([`MapBuilder::extending`]): its header and retrieval, and how many
    /// of `images` are its own.
    base: Option<(MapHeader, Retriever, usize)>,
}

/// One image offered to [`MapBuilder::add`].
pub struct NewImage<'v> {
    /// Stable id.
    pub id: String,
    /// Index into the map's scenes.
    pub scene: u32,
    /// The Point (place) it belongs to.
    pub point: u32,
    /// `world_from_camera`, map frame, the map's camera axes.
    pub world_from_camera: Isometry3<f64>,
    /// The recording's stamp, seconds (`None` for dataset views).
    pub stamp: Option<f64>,
    /// Colour.
    pub rgb: &'v RgbImage,
    /// Depth, metres (0 or non-finite = missing), the size of `rgb`.
    pub depth: &'v DepthMap,
    /// Instance labels, when the data has them.
    pub labels: Option<&'v LabelMap>,
    /// The camera (undistorted: maps hold rectified images).
    pub camera: Intrinsics,
}

impl<'a> MapBuilder<'a> {
    /// A builder for `preset`, describing images with `stage` (built from
    /// [`Preset::map_feature_config`]). Errors: an invalid preset, an ONNX global model that does not
    /// load.
    pub fn new(preset: &'a Preset, stage: &'a FeatureStage) -> Result<Self, PipelineError> {
        preset.validate()?;
        let global_model = match &preset.global_model {
            Some(p) if preset.global == "onnx" => Some(
                OnnxGlobal::load(p, &Default::default(), None, None)
                    .map_err(|e| PipelineError::Config(e.to_string()))?,
            ),
            _ => None,
        };
        Ok(Self {
            preset,
            stage,
            global_model,
            images: Vec::new(),
            onnx_desc: Vec::new(),
            header_camera: None,
            t0: Instant::now(),
            base: None,
        })
    }

    /// A builder that adds images to `base` (their poses in `base`'s frame and camera axes):
    /// [`MapBuilder::finish_extension`] keeps the base's images, header and learned retrieval (VLAD
    /// codebook or BoW vocabulary, the index's training) and appends the new images to its index.
    /// `stage` must describe images as the base's preset does. Errors: a preset that cannot describe
    /// images for this map, an ONNX model that does not load.
    pub fn extending(
        base: Map,
        preset: &'a Preset,
        stage: &'a FeatureStage,
    ) -> Result<Self, PipelineError> {
        preset.serves(&base.header.preset)?;
        let mut b = Self::new(preset, stage)?;
        b.header_camera = Some(base.header.intrinsics);
        let n = base.images.len();
        b.images = base.images;
        b.base = Some((base.header, base.retriever, n));
        Ok(b)
    }

    /// Images the map being extended had ([`MapBuilder::extending`]); 0 for a new map.
    pub fn base_len(&self) -> usize {
        self.base.as_ref().map_or(0, |b| b.2)
    }

    /// The images so far (the base's first).
    pub fn images(&self) -> &[MapImage] {
        &self.images
    }

    /// Finish a map made by [`MapBuilder::extending`]: the new images described with the base's
    /// own describer and appended to its index; the header keeps everything but the build time
    /// (now) and the build seconds (the base's plus this extension's). Errors: not an extension,
    /// the describer failing.
    pub fn finish_extension(self) -> Result<Map, PipelineError> {
        let Some((mut header, mut retriever, n)) = self.base else {
            return Err(PipelineError::Config(
                "finish_extension on a builder that extends no map".into(),
            ));
        };
        let descriptors = if let Describer::Onnx(_) = retriever.describer {
            self.onnx_desc
        } else {
            self.images[n..]
                .iter()
                .map(|im| retriever.describer.describe_features(&im.features()))
                .collect::<Result<Vec<_>, _>>()?
        };
        retriever.extend(descriptors)?;
        header.build_seconds += self.t0.elapsed().as_secs_f64();
        header.built_at_unix_s = Some(unix_now_s());
        Ok(Map {
            header,
            images: self.images,
            retriever,
            checksum: 0,
        })
    }

    /// Images added so far.
    pub fn len(&self) -> usize {
        self.images.len()
    }

    /// True before the first image.
    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }

    /// Extract and keep one image's features, 3D points and thumbnail. Errors: a distorted camera
    /// (undistort first), an extractor failure.
    pub fn add(&mut self, v: NewImage<'_>) -> Result<(), PipelineError> {
        let k = v.camera;
        if k.is_distorted() {
            return Err(PipelineError::Config(format!(
                "{}: the database camera has lens distortion {:?}; maps are built from rectified images (undistort them first)",
                v.id, k.distortion
            )));
        }
        self.header_camera.get_or_insert(k);
        let pixels = v.rgb.width as usize * v.rgb.height as usize;
        let f = self
            .stage
            .extractor
            .extract_at_most(v.rgb, self.preset.keypoints_for(pixels))?;
        if let Some(m) = &self.global_model {
            self.onnx_desc.push(Descriptor::Dense(
                m.describe(v.rgb)
                    .map_err(|e| PipelineError::Config(e.to_string()))?,
            ));
        }
        let (points, instances) = keypoint_points(&k, v.depth, v.labels, &f.keypoints);
        self.images.push(MapImage {
            id: v.id,
            scene: v.scene,
            point: v.point,
            world_from_camera: v.world_from_camera,
            stamp: v.stamp,
            descriptors: f.descriptors.iter().map(|&x| f16::from_f32(x)).collect(),
            dim: f.dim,
            binary: f.binary,
            keypoints: f.keypoints,
            scores: f.scores,
            points,
            instances,
            image_size: f.image_size,
            camera: k,
            thumb: Thumb::new(v.rgb, v.depth, &k),
            fine: crate::refine::fine_depth(v.rgb, v.depth, &k),
        });
        Ok(())
    }

    /// Learn the retrieval codebook or vocabulary on the images and index them. `scenes` names the
    /// world frames (each image's `scene` indexes it), `camera_axes` and `up_axis` go to the header
    /// ([`MapHeader`]). Errors: no image, a retrieval stage that cannot be trained, a model file the
    /// preset names that is missing.
    pub fn finish(
        self,
        map_id: &str,
        scenes: Vec<String>,
        camera_axes: pntr_core::CameraAxes,
        up_axis: &str,
        models_dir: &std::path::Path,
    ) -> Result<Map, PipelineError> {
        if self.images.is_empty() {
            return Err(PipelineError::Config("the map has no images".into()));
        }
        let preset = self.preset;
        let describer = match self.global_model {
            Some(m) => Describer::Onnx(m),
            None => train_describer(&preset.method(), &self.images)?,
        };
        let descriptors = if let Describer::Onnx(_) = describer {
            self.onnx_desc
        } else {
            self.images
                .iter()
                .map(|im| describer.describe_features(&im.features()))
                .collect::<Result<Vec<_>, _>>()?
        };
        let retriever = Retriever::build(describer, descriptors, preset.index_kind()?)?;
        Ok(Map {
            header: MapHeader {
                map_id: map_id.to_string(),
                // The index `auto` chose, so the header says what was built (and older readers,
                // which do not know `auto`, still load it).
                preset: Preset {
                    index: retriever
                        .index_kind()
                        .map_or_else(|| preset.index.clone(), |k| k.name()),
                    ..preset.clone()
                },
                models: model_identities(preset, models_dir)?,
                intrinsics: self.header_camera.unwrap_or_else(Intrinsics::hpointloc),
                camera_axes: camera_axes.name().into(),
                up_axis: up_axis.into(),
                scenes,
                built_by: format!("pntr {}", env!("CARGO_PKG_VERSION")),
                build_seconds: self.t0.elapsed().as_secs_f64(),
                built_at_unix_s: Some(unix_now_s()),
                sessions: Vec::new(),
                calibration: None,
            },
            images: self.images,
            retriever,
            checksum: 0,
        })
    }
}

/// Build a map of `scenes` with `preset`: extract features of every database image, learn the
/// retrieval codebook or vocabulary on them, index their global descriptors. `stage` describes the
/// images: build it from [`Preset::map_feature_config`] (the float backbone for `xfeat-mnn-int8` and `xfeat-mnn-bf16`).
/// `progress(done, total)` is called after every image.
pub fn build(
    map_id: &str,
    scenes: &[&SceneEntry],
    preset: &Preset,
    stage: &FeatureStage,
    models_dir: &std::path::Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Map, PipelineError> {
    let mut builder = MapBuilder::new(preset, stage)?;
    let mut total = 0;
    let mut readers = Vec::new();
    for s in scenes {
        for p in &s.points {
            let r = p.open()?;
            total += r.count(Role::Database);
            readers.push((p.clone(), r));
        }
    }
    if total == 0 {
        return Err(PipelineError::Config(
            "the dataset has no database images".into(),
        ));
    }
    let scene_names: Vec<String> = scenes.iter().map(|s| s.name.clone()).collect();
    for (entry, reader) in &readers {
        let scene = scene_names
            .iter()
            .position(|s| *s == entry.scene)
            .unwrap_or(0) as u32;
        for j in 0..reader.count(Role::Database) {
            let v = reader.view(Role::Database, j)?;
            builder.add(NewImage {
                id: entry.db_image_id(j),
                scene,
                point: entry.index,
                world_from_camera: v.world_from_camera,
                stamp: None,
                rgb: &v.rgb,
                depth: &v.depth,
                labels: v.semantic.as_ref(),
                camera: v.intrinsics,
            })?;
            progress(builder.len(), total);
        }
    }
    builder.finish(
        map_id,
        scene_names,
        pntr_core::CameraAxes::Habitat,
        &default_up_axis(),
        models_dir,
    )
}

/// Learn the describer on a sample of the map's descriptors (the best-scored keypoints of every image,
/// [`TRAINING_DESCRIPTORS`] in all), so training cost does not grow with the map.
fn train_describer(method: &Method, images: &[MapImage]) -> Result<Describer, PipelineError> {
    let per_image = (TRAINING_DESCRIPTORS / images.len()).max(16);
    let sample: Vec<Features> = images
        .iter()
        .map(|im| {
            let n = im.keypoints.len().min(per_image);
            Features {
                keypoints: im.keypoints[..n].to_vec(),
                scores: im.scores[..n].to_vec(),
                descriptors: im.descriptors[..n * im.dim]
                    .iter()
                    .map(|x| x.to_f32())
                    .collect(),
                dim: im.dim,
                binary: im.binary[..im.binary.len().min(per_image)].to_vec(),
                image_size: im.image_size,
            }
        })
        .collect();
    let mut d = Describer::train(method, &sample)?;
    if let Describer::Bow(voc) = &mut d {
        // IDF over every image's full descriptor set, not the sample.
        let all: Vec<Vec<[u8; 32]>> = images.iter().map(|im| im.binary.clone()).collect();
        voc.compute_idf(&all);
    }
    Ok(d)
}

/// Where a map built from a dataset is cached: `<dir>/<map_id>-<preset>.pntrmap`.
pub fn cache_path(dir: &std::path::Path, map_id: &str, preset: &str) -> PathBuf {
    dir.join(format!("{map_id}-{preset}.pntrmap"))
}
