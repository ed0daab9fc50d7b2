//! Where mapping gets its networks: the feature stage that describes a preset's map images and the
//! one that describes its queries (for the check and the map's own calibration), loaded from a
//! models folder with the caller's runtime options.

use std::path::{Path, PathBuf};

use pntr_features::config::{FeatureConfig, FeatureStage};
use pntr_features::runtime::RuntimeOptions;
use pntr_pipeline::preset::Preset;
use pntr_pipeline::PipelineError;

/// The models folder and the runtime options feature stages are loaded with. Each call loads the
/// models anew (a second or two for the ONNX ones).
#[derive(Debug, Clone)]
pub struct Stages {
    /// The models folder (`models/` of the repository, `--models`, `PNTR_MODELS`).
    pub models: PathBuf,
    /// Threads and device of the networks.
    pub runtime: RuntimeOptions,
}

impl Stages {
    /// Stages from `models` with `threads` ONNX Runtime threads on the CPU.
    pub fn new(models: &Path, threads: usize) -> Self {
        Self {
            models: models.to_path_buf(),
            runtime: RuntimeOptions {
                threads,
                ..RuntimeOptions::default()
            },
        }
    }

    /// The stage that describes `preset`'s map images ([`Preset::map_feature_config`]: the float
    /// backbone for the int8 and bf16 presets). Errors: `Config` naming the preset and the folder
    /// when a model does not load.
    pub fn map_stage(&self, preset: &Preset) -> Result<FeatureStage, PipelineError> {
        self.load(preset, preset.map_feature_config(self.models.clone()))
    }

    /// The stage that describes `preset`'s queries ([`Preset::feature_config`]). Errors: as
    /// [`Stages::map_stage`].
    pub fn query_stage(&self, preset: &Preset) -> Result<FeatureStage, PipelineError> {
        self.load(preset, preset.feature_config(self.models.clone()))
    }

    /// The query stage, or `map_stage` itself when the preset describes queries with the map's own
    /// network (no second model load).
    pub fn query_stage_or(
        &self,
        preset: &Preset,
        map_stage: FeatureStage,
    ) -> Result<FeatureStage, PipelineError> {
        if preset.extractor == preset.map_extractor() {
            Ok(map_stage)
        } else {
            self.query_stage(preset)
        }
    }

    fn load(&self, preset: &Preset, config: FeatureConfig) -> Result<FeatureStage, PipelineError> {
        FeatureConfig {
            runtime: self.runtime.clone(),
            ..config
        }
        .build()
        .map_err(|e| {
            PipelineError::Config(format!(
                "loading the models of preset {} from {}: {e}",
                preset.name,
                self.models.display()
            ))
        })
    }
}
