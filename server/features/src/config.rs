//! Choosing stages by name: one exhaustive match from configuration to built components.
//!
//! Names the CLI and the server accept: extractors `xfeat`, `xfeat-int8`, `xfeat-bf16`, `aliked`,
//! `orb`, `onnx`; matchers `lighterglue`, `lightglue`, `mnn`, `onnx`. `xfeat-int8` is XFeat's
//! backbone with int8 weights and activations (static quantization, keypoint heads kept in float:
//! `models/export.py`); `xfeat-bf16` is the float backbone run by OpenVINO in bfloat16
//! ([`crate::openvino`]); their descriptors are XFeat's, so they pair as `xfeat` does. Not every pair fits (LighterGlue was trained on XFeat's
//! 64-d descriptors, LightGlue here on ALIKED's 128-d ones; ORB's binary descriptors need Hamming
//! distance); an unfit pair is refused at start-up with the list of valid ones.

use std::path::PathBuf;
use std::sync::Arc;

use crate::lighterglue::LighterGlue;
use crate::mnn::{Mnn, MnnParams};
use crate::onnx_extractor::OnnxExtractor;
use crate::openvino::Precision;
use crate::orb::Orb;
use crate::runtime::{Engine, RuntimeOptions};
use crate::xfeat::{XFeat, XFeatParams, XFEAT_DIM};
use crate::{Extractor, FeatureError, Matcher};

/// Extractor names.
pub const EXTRACTORS: [&str; 6] = ["xfeat", "xfeat-int8", "xfeat-bf16", "aliked", "orb", "onnx"];
/// Matcher names.
pub const MATCHERS: [&str; 4] = ["lighterglue", "lightglue", "mnn", "onnx"];
/// Extractor/matcher pairs that fit.
pub const VALID_PAIRS: [(&str, &str); 15] = [
    ("xfeat", "lighterglue"),
    ("xfeat", "mnn"),
    ("xfeat", "onnx"),
    ("xfeat-int8", "lighterglue"),
    ("xfeat-int8", "mnn"),
    ("xfeat-int8", "onnx"),
    ("xfeat-bf16", "lighterglue"),
    ("xfeat-bf16", "mnn"),
    ("xfeat-bf16", "onnx"),
    ("aliked", "lightglue"),
    ("aliked", "mnn"),
    ("aliked", "onnx"),
    ("orb", "mnn"),
    ("onnx", "mnn"),
    ("onnx", "onnx"),
];

/// The model file of a built-in extractor or matcher in the models folder, `None` for the others
/// (`orb`, `mnn`, `onnx`, whose model, if any, is named by the caller).
pub fn model_file(name: &str) -> Option<&'static str> {
    match name {
        "xfeat" | "xfeat-bf16" => Some("xfeat_backbone.onnx"),
        "xfeat-int8" => Some("xfeat_backbone_int8.onnx"),
        "lighterglue" => Some("lighterglue.onnx"),
        "aliked" => Some("aliked_n16.onnx"),
        "lightglue" => Some("lightglue_aliked.onnx"),
        _ => None,
    }
}

/// Whether descriptors from extractor `a` mean the same as those from `b`: the same name, or two of
/// `xfeat`, `xfeat-int8` and `xfeat-bf16` (one network; the int8 one is quantized from it and its
/// descriptors agree with the float ones to a median cosine of 0.998, the bf16 one's to 0.9999, so a
/// map built with one serves queries of the others).
pub fn same_descriptors(a: &str, b: &str) -> bool {
    fn family(name: &str) -> &str {
        match name {
            "xfeat-int8" | "xfeat-bf16" => "xfeat",
            other => other,
        }
    }
    family(a) == family(b)
}

/// Descriptor length of ALIKED-n16.
pub const ALIKED_DIM: usize = 128;

/// Feature-stage configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureConfig {
    /// Extractor name (one of [`EXTRACTORS`]).
    pub extractor: String,
    /// Matcher name (one of [`MATCHERS`]).
    pub matcher: String,
    /// Folder holding the default models (`xfeat_backbone.onnx`, `lighterglue.onnx`).
    pub models_dir: PathBuf,
    /// Model file of the `onnx` extractor.
    pub extractor_model: Option<PathBuf>,
    /// Model file of the `onnx` matcher.
    pub matcher_model: Option<PathBuf>,
    /// Descriptor length the `onnx` matcher expects (default: the extractor's, 64 for xfeat).
    pub matcher_dim: Option<usize>,
    /// Keypoints kept per image.
    pub top_k: usize,
    /// How models run.
    pub runtime: RuntimeOptions,
}

impl Default for FeatureConfig {
    fn default() -> Self {
        Self {
            extractor: "xfeat".into(),
            matcher: "lighterglue".into(),
            models_dir: PathBuf::from("models"),
            extractor_model: None,
            matcher_model: None,
            matcher_dim: None,
            top_k: 1024,
            runtime: RuntimeOptions::default(),
        }
    }
}

/// The built feature stage.
#[derive(Clone)]
pub struct FeatureStage {
    /// The extractor.
    pub extractor: Arc<dyn Extractor>,
    /// The matcher.
    pub matcher: Arc<dyn Matcher>,
}

impl std::fmt::Debug for FeatureStage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "FeatureStage({} + {})",
            self.extractor.name(),
            self.matcher.name()
        )
    }
}

impl FeatureStage {
    /// Run each model once on a small synthetic image, so the first request does not pay for ONNX
    /// Runtime's lazy initialisation (allocations, kernel selection, CUDA context).
    pub fn warm_up(&self) -> Result<(), FeatureError> {
        let (w, h) = (128u32, 96u32);
        let data: Vec<u8> = (0..w * h * 3)
            .map(|i| {
                let (x, y) = ((i / 3) % w, (i / 3) / w);
                (((x / 8 + y / 8) % 2) * 200 + (x * 7 + y * 13) % 40) as u8
            })
            .collect();
        let img =
            pntr_core::RgbImage::new(w, h, data).map_err(|e| FeatureError::Input(e.to_string()))?;
        let f = self.extractor.extract(&img)?;
        self.matcher.match_features(&f, &f)?;
        Ok(())
    }
}

fn pairs_list() -> String {
    VALID_PAIRS
        .iter()
        .map(|(e, m)| format!("{e}+{m}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn need(path: &Option<PathBuf>, what: &str) -> Result<PathBuf, FeatureError> {
    path.clone().ok_or_else(|| {
        FeatureError::Input(format!(
            "the `onnx` {what} needs a model file ({what}_model)"
        ))
    })
}

impl FeatureConfig {
    /// Check names and pairing without loading anything.
    pub fn validate(&self) -> Result<(), FeatureError> {
        let (e, m) = (self.extractor.as_str(), self.matcher.as_str());
        if !EXTRACTORS.contains(&e) {
            return Err(FeatureError::Input(format!(
                "unknown extractor `{e}`; valid: {}",
                EXTRACTORS.join(", ")
            )));
        }
        if !MATCHERS.contains(&m) {
            return Err(FeatureError::Input(format!(
                "unknown matcher `{m}`; valid: {}",
                MATCHERS.join(", ")
            )));
        }
        if !VALID_PAIRS.contains(&(e, m)) {
            return Err(FeatureError::Input(format!(
                "extractor `{e}` does not fit matcher `{m}`; valid pairs: {}",
                pairs_list()
            )));
        }
        if self.top_k == 0 {
            return Err(FeatureError::Input("top_k must be at least 1".into()));
        }
        Ok(())
    }

    /// Validate, then load the models.
    pub fn build(&self) -> Result<FeatureStage, FeatureError> {
        self.validate()?;
        let extractor: Arc<dyn Extractor> = match self.extractor.as_str() {
            name @ ("xfeat" | "xfeat-int8" | "xfeat-bf16") => {
                let path = self
                    .models_dir
                    .join(model_file(name).expect("xfeat models are named"));
                if name == "xfeat-int8" && !path.is_file() {
                    return Err(FeatureError::Model {
                        path: path.display().to_string(),
                        message: "not found: the int8 backbone is made from \
                                  xfeat_backbone.onnx by models/quantize.py"
                            .into(),
                    });
                }
                let mut runtime = self.runtime.clone();
                if name == "xfeat-bf16" {
                    runtime.engine = Engine::OpenVino(Precision::Bf16);
                }
                Arc::new(XFeat::load(
                    &path,
                    XFeatParams {
                        top_k: self.top_k,
                        runtime,
                        ..XFeatParams::default()
                    },
                )?)
            }
            "aliked" => Arc::new(OnnxExtractor::load_named(
                &self.models_dir.join("aliked_n16.onnx"),
                &self.runtime,
                self.top_k,
                Some(32),
                "aliked",
            )?),
            "orb" => Arc::new(Orb { top_k: self.top_k }),
            "onnx" => Arc::new(OnnxExtractor::load(
                &need(&self.extractor_model, "extractor")?,
                &self.runtime,
                self.top_k,
            )?),
            other => unreachable!("validated extractor name {other}"),
        };
        let matcher: Arc<dyn Matcher> = match self.matcher.as_str() {
            "lighterglue" => Arc::new(LighterGlue::load(
                &self.models_dir.join("lighterglue.onnx"),
                &self.runtime,
            )?),
            "lightglue" => {
                let path = self.models_dir.join("lightglue_aliked.onnx");
                if !path.is_file() {
                    return Err(FeatureError::Model {
                        path: path.display().to_string(),
                        message:
                            "not found: the 48 MB LightGlue-for-ALIKED model is not committed; \
                                  produce it with models/export.py"
                                .into(),
                    });
                }
                Arc::new(LighterGlue::load_custom(
                    &path,
                    &self.runtime,
                    ALIKED_DIM,
                    "lightglue",
                )?)
            }
            "mnn" => Arc::new(Mnn {
                params: MnnParams::default(),
            }),
            "onnx" => Arc::new(LighterGlue::load_custom(
                &need(&self.matcher_model, "matcher")?,
                &self.runtime,
                self.matcher_dim.unwrap_or(match self.extractor.as_str() {
                    "aliked" => ALIKED_DIM,
                    _ => XFEAT_DIM,
                }),
                "onnx",
            )?),
            other => unreachable!("validated matcher name {other}"),
        };
        let stage = FeatureStage { extractor, matcher };
        stage.warm_up()?;
        Ok(stage)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_pairs_are_checked() {
        let mut c = FeatureConfig::default();
        c.validate().unwrap();
        c.extractor = "sift".into();
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("unknown extractor `sift`")
                && e.contains("xfeat, xfeat-int8, xfeat-bf16, aliked, orb, onnx"),
            "{e}"
        );
        c.extractor = "onnx".into();
        c.matcher = "lighterglue".into();
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("does not fit") && e.contains("xfeat+lighterglue"),
            "{e}"
        );
        c.extractor = "orb".into();
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("`orb` does not fit matcher `lighterglue`") && e.contains("orb+mnn"),
            "{e}"
        );
        c.matcher = "glue".into();
        assert!(c
            .validate()
            .unwrap_err()
            .to_string()
            .contains("unknown matcher `glue`"));
    }
}
