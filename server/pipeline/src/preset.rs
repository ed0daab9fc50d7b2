//! Named presets: one string picks every stage (hloc-style), so a map, a server and an evaluation
//! agree on what ran. The preset is stored in the map header; the server and `pntr eval` refuse a
//! preset whose extractor's descriptors differ from those the map was built with (`xfeat`, its int8
//! quantization `xfeat-int8` and its bf16 run `xfeat-bf16` share theirs).

use std::path::PathBuf;

use pntr_features::config::FeatureConfig;
use pntr_retrieval::bow::BowParams;
use pntr_retrieval::global::Method;
use pntr_retrieval::index::IndexKind;
use serde::{Deserialize, Serialize};

use crate::PipelineError;

/// Registration solver.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Solver {
    /// TEASER-style certifiable robust 3D-3D registration (default).
    Teaser,
    /// ICP on the matched 3D pairs from the identity (the paper's ICP rows).
    Icp,
    /// PnP + RANSAC on query pixels and database 3D points (classical).
    Pnp,
}

/// Every choice of the pipeline.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Preset {
    /// The preset's name.
    pub name: String,
    /// Global descriptor: `vlad`, `bow` or `onnx`.
    pub global: String,
    /// VLAD codewords.
    pub vlad_words: usize,
    /// faiss index for dense descriptors: `auto` (the default: exact search below 4096 images,
    /// PCA-whitening to 512 dimensions from there on when the descriptor is longer), `flat`,
    /// `hnsw32`, `ivf1024`, `pcaw256`. A built map's header records what `auto` chose.
    pub index: String,
    /// Model of the `onnx` global descriptor.
    pub global_model: Option<PathBuf>,
    /// Extractor name (`xfeat`, `xfeat-int8`, `aliked`, `orb`, `onnx`).
    pub extractor: String,
    /// Matcher name (`lighterglue`, `lightglue`, `mnn`, `onnx`).
    pub matcher: String,
    /// Keypoints per image of up to [`KEYPOINTS_REFERENCE_PIXELS`] (HPointLoc's 256x256 frames,
    /// which the counts were chosen for); see [`Preset::keypoints_for`] for larger images.
    pub keypoints: usize,
    /// Most keypoints per image for images larger than [`KEYPOINTS_REFERENCE_PIXELS`]: the count
    /// grows with the described image's pixels up to this many ([`Preset::keypoints_for`]), the
    /// same for the map's images and the queries. 0 (also for maps written before this field) keeps
    /// `keypoints` at every size.
    #[serde(default)]
    pub keypoints_max: usize,
    /// Retrieval candidates considered per query (k of top-k).
    pub candidates: usize,
    /// Global candidates re-ranked by a vote of their strongest keypoints before the `candidates`
    /// best go on ([`crate::shortlist`]); 0 (the default, also for maps written before this field)
    /// chooses by the map's size ([`crate::shortlist::automatic_depth`]). Used when `rerank` is on.
    #[serde(default)]
    pub shortlist: usize,
    /// Re-rank the candidates by a cheap geometric check (MNN matches registered with the solver) and
    /// run the matcher only on the best `final_candidates`; without it, the matcher runs on all.
    pub rerank: bool,
    /// Candidates the (learned) matcher runs on after re-ranking.
    pub final_candidates: usize,
    /// Registration solver.
    pub solver: Solver,
    /// Fewest inliers for a LOCALIZED answer.
    pub min_inliers: usize,
    /// For a frame whose depth is noisy (a real sensor's, measured on the frame:
    /// [`crate::depth_noise`]), a TEASER candidate that the fixed noise bound cannot register is
    /// registered again with each correspondence's bound grown by this many standard deviations of
    /// the depth noise at its range (added in quadrature). Default 3 (also for maps written before
    /// this field); 0 keeps the fixed bound alone.
    #[serde(default = "default_depth_noise_sigmas")]
    pub depth_noise_sigmas: f64,
    /// Working resolution of a map built from recordings, pixels: a frame with more pixels is
    /// resampled to this many (aspect ratio kept, [`crate::camera::to_map_scale`]) before it is
    /// judged and described, and every query follows the map's scale on the server, so a 640x480 or
    /// 1280x720 camera costs about what this many pixels cost. 0 (the default, also for maps written
    /// before this field) keeps the camera's own resolution. Only map building reads it: serving a
    /// map with another preset keeps the scale the map was built at.
    #[serde(default)]
    pub max_image_pixels: usize,
}

/// Pixels of the image size [`Preset::keypoints`] was chosen for: HPointLoc's 256x256 frames.
pub const KEYPOINTS_REFERENCE_PIXELS: usize = 256 * 256;

/// [`Preset::keypoints_max`] of the XFeat + MNN presets that describe frames at the camera's own
/// size: twice their 512, reached from 131,072 pixels on (a 640x480 frame has 4.7 times a 256x256
/// one's pixels). Measured on real 640x480 Kinect frames (BENCHMARKS.md, "Real recordings: more
/// keypoints for larger frames"): with 512 keypoints a VGA frame's pose rests on a few dozen matches
/// and comes out loosely held; with 1024 more frames localize within (5 cm, 5 deg) under the
/// covariance gate ([`crate::pipeline::MAX_ROTATION_SIGMA_DEG`]) for about 30 % more server time,
/// where 2048 doubled the time for two frames more.
pub const XFEAT_MNN_KEYPOINTS_MAX: usize = 1024;

/// [`Preset::max_image_pixels`] of the `-qvga` presets: 320x240, about a 256x256 frame's cost.
pub const QVGA_PIXELS: usize = 320 * 240;

/// [`Preset::depth_noise_sigmas`] of every built-in preset, and of maps written before the field.
pub const DEFAULT_DEPTH_NOISE_SIGMAS: f64 = 3.0;

fn default_depth_noise_sigmas() -> f64 {
    DEFAULT_DEPTH_NOISE_SIGMAS
}

/// Names of the built-in presets.
pub const PRESETS: [&str; 11] = [
    "fast",
    "fast-norerank",
    "fast-icp",
    "accurate",
    "accurate-icp",
    "classical",
    "xfeat-mnn",
    "xfeat-mnn-int8",
    "xfeat-mnn-bf16",
    "xfeat-mnn-qvga",
    "xfeat-mnn-bf16-qvga",
];

/// The default preset: the best trade-off measured (BENCHMARKS.md, "Pipeline presets"): on the synthetic
/// scenes XFeat + MNN matches `fast` (LighterGlue) within a query or two in every recall column at about
/// a third of the time. Re-measure on real data before relying on that: learned matching is what holds
/// up under lighting change and blur, which the renderer does not model.
pub const DEFAULT_PRESET: &str = "xfeat-mnn";

impl Preset {
    /// A built-in preset by name.
    pub fn named(name: &str) -> Result<Self, PipelineError> {
        let base = Self {
            name: name.to_string(),
            global: "vlad".into(),
            vlad_words: 64,
            index: "auto".into(),
            global_model: None,
            extractor: "xfeat".into(),
            matcher: "lighterglue".into(),
            keypoints: 512,
            keypoints_max: 0,
            candidates: 5,
            shortlist: 0,
            rerank: true,
            final_candidates: 1,
            solver: Solver::Teaser,
            min_inliers: 12,
            depth_noise_sigmas: DEFAULT_DEPTH_NOISE_SIGMAS,
            max_image_pixels: 0,
        };
        Ok(match name {
            "fast" => base,
            "fast-norerank" => Self {
                candidates: 1,
                rerank: false,
                ..base
            },
            "fast-icp" => Self {
                solver: Solver::Icp,
                ..base
            },
            "accurate" => Self {
                extractor: "aliked".into(),
                matcher: "lightglue".into(),
                ..base
            },
            "accurate-icp" => Self {
                extractor: "aliked".into(),
                matcher: "lightglue".into(),
                solver: Solver::Icp,
                ..base
            },
            "classical" => Self {
                global: "bow".into(),
                extractor: "orb".into(),
                matcher: "mnn".into(),
                keypoints: 1024,
                solver: Solver::Pnp,
                ..base
            },
            "xfeat-mnn" => Self {
                keypoints_max: XFEAT_MNN_KEYPOINTS_MAX,
                matcher: "mnn".into(),
                ..base
            },
            "xfeat-mnn-int8" => Self {
                keypoints_max: XFEAT_MNN_KEYPOINTS_MAX,
                extractor: "xfeat-int8".into(),
                matcher: "mnn".into(),
                ..base
            },
            "xfeat-mnn-bf16" => Self {
                keypoints_max: XFEAT_MNN_KEYPOINTS_MAX,
                extractor: "xfeat-bf16".into(),
                matcher: "mnn".into(),
                ..base
            },
            "xfeat-mnn-qvga" => Self {
                matcher: "mnn".into(),
                max_image_pixels: QVGA_PIXELS,
                ..base
            },
            "xfeat-mnn-bf16-qvga" => Self {
                extractor: "xfeat-bf16".into(),
                matcher: "mnn".into(),
                max_image_pixels: QVGA_PIXELS,
                ..base
            },
            other => {
                return Err(PipelineError::Config(format!(
                    "unknown preset `{other}`; presets: {}",
                    PRESETS.join(", ")
                )))
            }
        })
    }

    /// The same pipeline with XFeat's backbone run in bfloat16 on OpenVINO: `xfeat-mnn` ->
    /// `xfeat-mnn-bf16`, `xfeat-mnn-qvga` -> `xfeat-mnn-bf16-qvga`, every other field (a map's
    /// own global model among them) kept. `None` for every other preset (already bf16, int8, or
    /// not XFeat). The twin serves the map ([`Preset::serves`]: the same descriptors) and is scored
    /// by the same calibration ([`Preset::calibration_preset`]); its answers were measured to
    /// match the float model's within noise (BENCHMARKS.md, "bf16 XFeat on OpenVINO").
    pub fn bf16_twin(&self) -> Option<Preset> {
        let name = match (self.name.as_str(), self.extractor.as_str()) {
            ("xfeat-mnn", "xfeat") => "xfeat-mnn-bf16",
            ("xfeat-mnn-qvga", "xfeat") => "xfeat-mnn-bf16-qvga",
            _ => return None,
        };
        Some(Preset {
            name: name.into(),
            extractor: "xfeat-bf16".into(),
            ..self.clone()
        })
    }

    /// The preset whose confidence calibration scores this one's answers: its own name, except
    /// `xfeat-mnn-int8` and `xfeat-mnn-bf16`, which run `xfeat-mnn`'s pipeline with the int8 or the
    /// bf16 backbone and are scored by `xfeat-mnn`'s calibration (measured to hold: BENCHMARKS.md,
    /// "int8 XFeat", "bf16 XFeat on OpenVINO"), and the `-qvga` presets, which are those pipelines
    /// on images of at most [`QVGA_PIXELS`] (the same as theirs on frames that small, such as
    /// HPointLoc's 256x256). One way only: a calibration fitted for any of them still warns when
    /// loaded for `xfeat-mnn`, since nothing measured that direction.
    pub fn calibration_preset(&self) -> &str {
        match self.name.as_str() {
            "xfeat-mnn-int8" | "xfeat-mnn-bf16" | "xfeat-mnn-qvga" | "xfeat-mnn-bf16-qvga" => {
                "xfeat-mnn"
            }
            name => name,
        }
    }

    /// Whether this preset can run queries against a map built with preset `built`: its
    /// descriptors (extractor, [`pntr_features::config::same_descriptors`]) and global descriptor
    /// must be the map's. The error names both presets and, for a map of XFeat, the presets that can.
    pub fn serves(&self, built: &Preset) -> Result<(), PipelineError> {
        let can = |p: &Preset| {
            pntr_features::config::same_descriptors(&built.extractor, &p.extractor)
                && built.global == p.global
        };
        if can(self) {
            return Ok(());
        }
        let able: Vec<&str> = PRESETS
            .iter()
            .copied()
            .filter(|n| Preset::named(n).is_ok_and(|p| can(&p)))
            .collect();
        Err(PipelineError::Config(format!(
            "the map was built with {} + {} (preset {}); preset {} uses {} + {}, which that map \
             cannot match (presets that can: {})",
            built.global,
            built.map_extractor(),
            built.name,
            self.name,
            self.global,
            self.extractor,
            if able.is_empty() {
                "none built in".to_string()
            } else {
                able.join(", ")
            }
        )))
    }

    /// Check the combination before anything is loaded.
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |m: String| Err(PipelineError::Config(format!("preset {}: {m}", self.name)));
        match (self.global.as_str(), self.extractor.as_str()) {
            ("bow", "orb")
            | ("vlad", "xfeat" | "xfeat-int8" | "xfeat-bf16" | "aliked" | "onnx")
            | ("onnx", _) => {}
            ("bow", e) => return bad(format!("bow needs the orb extractor, not {e}")),
            ("vlad", e) => return bad(format!("vlad needs float descriptors; {e} has none")),
            (g, _) => return bad(format!("unknown global descriptor `{g}` (vlad, bow, onnx)")),
        }
        if self.global == "onnx" && self.global_model.is_none() {
            return bad("the onnx global descriptor needs global_model".into());
        }
        IndexKind::parse(&self.index).map_err(|e| PipelineError::Config(e.to_string()))?;
        if self.candidates == 0 || self.final_candidates == 0 || self.keypoints == 0 {
            return bad("candidates, final_candidates and keypoints must be positive".into());
        }
        if !(self.depth_noise_sigmas.is_finite() && self.depth_noise_sigmas >= 0.0) {
            return bad(format!(
                "depth_noise_sigmas is {}; it must be 0 (off) or a positive number of standard deviations",
                self.depth_noise_sigmas
            ));
        }
        self.feature_config(PathBuf::new())
            .validate()
            .map_err(|e| PipelineError::Config(e.to_string()))
    }

    /// Keypoints to describe an image of `pixels` pixels with (after any resampling to the map's
    /// scale): [`Self::keypoints`] up to [`KEYPOINTS_REFERENCE_PIXELS`], then in proportion to the
    /// pixels (the same density) up to [`Self::keypoints_max`]; `keypoints` at every size when that
    /// is 0 or smaller. The map's images and the queries follow the same rule, so both sides of a
    /// match are described alike.
    pub fn keypoints_for(&self, pixels: usize) -> usize {
        let most = self.keypoints_max.max(self.keypoints);
        let scaled = (self.keypoints as f64 * pixels as f64 / KEYPOINTS_REFERENCE_PIXELS as f64)
            .round() as usize;
        scaled.clamp(self.keypoints, most)
    }

    /// The most keypoints any image asks of the extractor ([`Self::keypoints_for`]): its
    /// configured `top_k`.
    pub fn extractor_top_k(&self) -> usize {
        self.keypoints_max.max(self.keypoints)
    }

    /// The feature-stage configuration (models from `models_dir`).
    pub fn feature_config(&self, models_dir: PathBuf) -> FeatureConfig {
        FeatureConfig {
            extractor: self.extractor.clone(),
            matcher: self.matcher.clone(),
            models_dir,
            top_k: self.extractor_top_k(),
            ..FeatureConfig::default()
        }
    }

    /// The extractor that describes the map's images: the preset's own, except for `xfeat-int8`
    /// and `xfeat-bf16`, whose maps are described by the float `xfeat` (the same descriptor space;
    /// int8 on both sides cost precision where int8 on the query side alone did not: BENCHMARKS.md,
    /// "int8 XFeat"). Map building is offline, so it keeps the float network's accuracy, and one
    /// map serves all three.
    pub fn map_extractor(&self) -> &str {
        match self.extractor.as_str() {
            "xfeat-int8" | "xfeat-bf16" => "xfeat",
            other => other,
        }
    }

    /// The feature-stage configuration that builds this preset's maps ([`Self::map_extractor`]).
    pub fn map_feature_config(&self, models_dir: PathBuf) -> FeatureConfig {
        FeatureConfig {
            extractor: self.map_extractor().to_string(),
            ..self.feature_config(models_dir)
        }
    }

    /// How the global describer is learned.
    pub fn method(&self) -> Method {
        if self.global == "bow" {
            Method::Bow(BowParams::default())
        } else {
            Method::Vlad {
                words: self.vlad_words,
            }
        }
    }

    /// The parsed index kind.
    pub fn index_kind(&self) -> Result<IndexKind, PipelineError> {
        IndexKind::parse(&self.index).map_err(|e| PipelineError::Config(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_named_preset_validates_and_unknown_names_are_listed() {
        for name in PRESETS {
            Preset::named(name).unwrap().validate().unwrap();
        }
        let e = Preset::named("nope").unwrap_err().to_string();
        assert!(e.contains("fast") && e.contains("classical"), "{e}");
        let bad = Preset {
            global: "bow".into(),
            ..Preset::named("fast").unwrap()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("orb"));
        let bad = Preset {
            depth_noise_sigmas: -1.0,
            ..Preset::named("xfeat-mnn").unwrap()
        };
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("depth_noise_sigmas"));
        // The int8 preset queries with the int8 backbone, describes maps with the float one and is
        // scored by the float preset's calibration.
        let int8 = Preset::named("xfeat-mnn-int8").unwrap();
        assert_eq!(int8.feature_config(PathBuf::new()).extractor, "xfeat-int8");
        assert_eq!(int8.map_feature_config(PathBuf::new()).extractor, "xfeat");
        assert_eq!(int8.calibration_preset(), "xfeat-mnn");
        for (float, twin) in [
            ("xfeat-mnn", "xfeat-mnn-bf16"),
            ("xfeat-mnn-qvga", "xfeat-mnn-bf16-qvga"),
        ] {
            let t = Preset::named(float).unwrap().bf16_twin().unwrap();
            assert_eq!(t, Preset::named(twin).unwrap(), "{float}'s twin is {twin}");
            t.serves(&Preset::named(float).unwrap()).unwrap();
            assert_eq!(t.calibration_preset(), "xfeat-mnn");
        }
        for other in ["xfeat-mnn-bf16", "xfeat-mnn-int8", "fast", "classical"] {
            assert!(
                Preset::named(other).unwrap().bf16_twin().is_none(),
                "{other}"
            );
        }
        let bf16 = Preset::named("xfeat-mnn-bf16").unwrap();
        assert_eq!(bf16.feature_config(PathBuf::new()).extractor, "xfeat-bf16");
        assert_eq!(bf16.map_feature_config(PathBuf::new()).extractor, "xfeat");
        assert_eq!(bf16.calibration_preset(), "xfeat-mnn");
        let qvga = Preset::named("xfeat-mnn-bf16-qvga").unwrap();
        assert_eq!(qvga.feature_config(PathBuf::new()).extractor, "xfeat-bf16");
        assert_eq!(qvga.max_image_pixels, QVGA_PIXELS);
        assert_eq!(qvga.calibration_preset(), "xfeat-mnn");
        qvga.serves(&Preset::named("xfeat-mnn").unwrap()).unwrap();
        let fast = Preset::named("fast").unwrap();
        assert_eq!(fast.map_extractor(), "xfeat");
        assert_eq!(fast.calibration_preset(), "fast");
    }

    #[test]
    fn keypoints_grow_with_the_image_up_to_the_presets_most() {
        let p = Preset::named("xfeat-mnn").unwrap();
        // HPointLoc's 256x256 frames and anything smaller: the preset's 512.
        assert_eq!(p.keypoints_for(256 * 256), 512);
        assert_eq!(p.keypoints_for(128 * 128), 512);
        // The same density above it, up to the most.
        assert_eq!(p.keypoints_for(320 * 240), 600);
        assert_eq!(p.keypoints_for(362 * 362), 1024);
        assert_eq!(p.keypoints_for(640 * 480), XFEAT_MNN_KEYPOINTS_MAX);
        assert_eq!(p.keypoints_for(1280 * 720), XFEAT_MNN_KEYPOINTS_MAX);
        assert_eq!(p.extractor_top_k(), XFEAT_MNN_KEYPOINTS_MAX);
        assert_eq!(
            p.feature_config(PathBuf::new()).top_k,
            XFEAT_MNN_KEYPOINTS_MAX
        );
        // The -qvga presets keep their budget: 512 at every size.
        let q = Preset::named("xfeat-mnn-qvga").unwrap();
        assert_eq!(q.keypoints_for(640 * 480), 512);
        // A map written before the field (no `keypoints_max` in its header) keeps its count.
        let mut old = serde_json::to_value(&p).unwrap();
        old.as_object_mut().unwrap().remove("keypoints_max");
        let old: Preset = serde_json::from_value(old).unwrap();
        assert_eq!(old.keypoints_max, 0);
        assert_eq!(old.keypoints_for(640 * 480), 512);
        assert_eq!(old.extractor_top_k(), 512);
    }
}
