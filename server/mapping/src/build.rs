//! Building a map from HPointLoc-layout Point files ([`build`]) or image by image ([`MapBuilder`],
//! what maps from recordings and extensions use): per database image its pose, keypoints, local
//! descriptors (float ones stored as f16, which halves the largest part of the map for a relative
//! error near 1e-3; binary ORB ones as they are), the 3D point of every keypoint in the camera's
//! OpenCV frame from the image's own depth (NaN where the depth is invalid: the keypoint stays in
//! place, so indices never shift and pairs never misalign), and the instance id under it; then the
//! retrieval stage learned on them.

use std::time::Instant;

use half::f16;
use nalgebra::Isometry3;
use pntr_core::{DepthMap, Intrinsics, LabelMap, RgbImage};
use pntr_dataset::{Role, SceneEntry};
use pntr_features::config::FeatureStage;
use pntr_features::Features;
use pntr_retrieval::global::{Describer, Descriptor, Method, Retriever};
use pntr_retrieval::onnx_global::OnnxGlobal;

use pntr_pipeline::map::{
    default_up_axis, keypoint_points, unix_now_s, Map, MapHeader, MapImage, ModelIdentity,
};
use pntr_pipeline::preset::Preset;
use pntr_pipeline::verify::Thumb;
use pntr_pipeline::PipelineError;

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
            fine: pntr_pipeline::refine::fine_depth(v.rgb, v.depth, &k),
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
