//! Calibrated confidence: the probability that a pose is within (1 m, 10 deg) of the truth, from the
//! verification [`Evidence`], by logistic regression (Platt-style) fitted on labelled answers.
//!
//! The file (`models/calibration.json`, embedded in the binaries as the default) is JSON:
//! `{"format": "pntr-calibration", "version": 1, "features": [names], "mean": [..], "scale": [..],
//! "weights": [..], "bias": b, "threshold": t, "preset": "...", "fitted_on": {...}, "checksum": "..."}`.
//! `checksum` is FNV-1a (hex) of the canonical JSON of every other field; a file whose checksum, format,
//! version or feature names differ is refused, so a hand-edited or truncated calibration never
//! silently changes what LOCALIZED means. `pntr calibrate` refits it on a user's data.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::verify::{Evidence, EVIDENCE_NAMES};
use crate::PipelineError;

/// The `format` value of a calibration file.
pub const FORMAT: &str = "pntr-calibration";
/// The calibration file version this build reads and writes.
pub const VERSION: u32 = 1;
/// The calibration shipped with the models (`models/calibration.json`), embedded at build time.
pub const EMBEDDED: &str = include_str!("../../../models/calibration.json");

/// What a calibration was fitted on.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FitInfo {
    /// Labelled candidate poses used.
    pub samples: usize,
    /// Of which positives (within 1 m, 10 deg).
    pub positives: usize,
    /// Queries they came from (in-map, with robot effects, and out-of-map).
    #[serde(default)]
    pub queries: usize,
    /// Datasets (in-map and negatives) the samples came from.
    pub datasets: Vec<String>,
    /// Expected calibration error of the queries' answers on the fitting set (10 bins).
    pub ece: f64,
    /// Precision at (1 m, 10 deg) of the queries' answers at or above the threshold, fitting set.
    pub precision_at_threshold: f64,
    /// Share of the queries answered right that stay LOCALIZED at the threshold, on the fitting set.
    pub recall_at_threshold: f64,
    /// When it was fitted (RFC 3339 date), free text.
    pub date: String,
}

/// A fitted logistic model over [`Evidence`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always [`VERSION`].
    pub version: u32,
    /// Feature names, [`EVIDENCE_NAMES`].
    pub features: Vec<String>,
    /// Per-feature mean used for standardisation.
    pub mean: Vec<f64>,
    /// Per-feature scale (standard deviation) used for standardisation.
    pub scale: Vec<f64>,
    /// Weights of the standardised features.
    pub weights: Vec<f64>,
    /// Intercept.
    pub bias: f64,
    /// Recommended LOCALIZED threshold on the probability (chosen for precision when fitted).
    pub threshold: f64,
    /// Preset whose answers it was fitted on.
    pub preset: String,
    /// Provenance.
    pub fitted_on: FitInfo,
    /// FNV-1a of the other fields (see the module docs).
    #[serde(default)]
    pub checksum: String,
}

fn bad(path: &Path, m: impl std::fmt::Display) -> PipelineError {
    PipelineError::Io {
        path: path.to_path_buf(),
        message: format!("calibration: {m}"),
    }
}

impl Calibration {
    /// The embedded default.
    pub fn embedded() -> Self {
        Self::parse(EMBEDDED, Path::new("<embedded models/calibration.json>"))
            .expect("the embedded calibration is valid (checked by a test)")
    }

    /// The checksum of every field but `checksum`.
    pub fn compute_checksum(&self) -> String {
        let mut c = self.clone();
        c.checksum.clear();
        let bytes = serde_json::to_vec(&c).expect("plain data serialises");
        format!("{:016x}", pntr_core::bytes::fnv1a(&bytes))
    }

    /// Parse and check a calibration (`path` names it in errors).
    pub fn parse(text: &str, path: &Path) -> Result<Self, PipelineError> {
        let c: Calibration = serde_json::from_str(text).map_err(|e| bad(path, e))?;
        if c.format != FORMAT {
            return Err(bad(path, format!("format `{}`, want `{FORMAT}`", c.format)));
        }
        if c.version != VERSION {
            return Err(bad(
                path,
                format!("version {}; this build reads version {VERSION}", c.version),
            ));
        }
        if c.checksum != c.compute_checksum() {
            return Err(bad(
                path,
                "checksum mismatch (the file was changed or damaged; refit with `pntr calibrate`)",
            ));
        }
        let n = EVIDENCE_NAMES.len();
        if c.features != EVIDENCE_NAMES {
            return Err(bad(
                path,
                format!(
                    "features {:?}; this build computes {:?} (a calibration from another build: \
                     refit it with `pntr calibrate`)",
                    c.features, EVIDENCE_NAMES
                ),
            ));
        }
        if c.mean.len() != n || c.scale.len() != n || c.weights.len() != n {
            return Err(bad(
                path,
                format!("mean, scale and weights need {n} values"),
            ));
        }
        let finite = c
            .mean
            .iter()
            .chain(&c.scale)
            .chain(&c.weights)
            .chain([&c.bias, &c.threshold])
            .all(|v| v.is_finite());
        if !finite || c.scale.iter().any(|&s| s <= 0.0) || !(0.0..=1.0).contains(&c.threshold) {
            return Err(bad(
                path,
                "values must be finite, scales positive, threshold in 0..1",
            ));
        }
        Ok(c)
    }

    /// Read and check a calibration file.
    pub fn load(path: &Path) -> Result<Self, PipelineError> {
        let text = std::fs::read_to_string(path).map_err(|e| bad(path, e))?;
        Self::parse(&text, path)
    }

    /// Write atomically (temporary name, fsync, rename), with the checksum filled in.
    pub fn save(&self, path: &Path) -> Result<(), PipelineError> {
        let mut c = self.clone();
        c.checksum = c.compute_checksum();
        let text = serde_json::to_string_pretty(&c).map_err(|e| bad(path, e))? + "\n";
        let tmp = PathBuf::from(format!("{}.partial-{}", path.display(), std::process::id()));
        let write = || -> std::io::Result<()> {
            use std::io::Write;
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(text.as_bytes())?;
            f.sync_all()?;
            std::fs::rename(&tmp, path)
        };
        write().map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            bad(path, e)
        })
    }

    /// Probability in 0..1 that the pose with this evidence is within (1 m, 10 deg).
    pub fn probability(&self, e: &Evidence) -> f64 {
        let x = model_inputs(e);
        let z = self.bias
            + x.iter()
                .zip(&self.mean)
                .zip(&self.scale)
                .zip(&self.weights)
                .map(|(((v, m), s), w)| w * (v - m) / s)
                .sum::<f64>();
        sigmoid(z)
    }
}

/// The model's inputs: the evidence with shares on a logit scale (so 0.95 and 0.99 agreement differ
/// as much as they matter), violation shares on a log scale and correlations through atanh (Fisher's
/// z); counts stay as they are.
pub fn model_inputs(e: &Evidence) -> [f64; N_FEATURES] {
    const EPS: f64 = 0.02;
    let logit = |a: f64| {
        let a = a.clamp(0.0, 1.0);
        ((a + EPS) / (1.0 - a + EPS)).ln()
    };
    let log = |a: f64| (a.clamp(0.0, 1.0) + EPS).ln();
    let z = |r: f64| r.clamp(-0.99, 0.99).atanh();
    let v = e.values();
    std::array::from_fn(|j| match EVIDENCE_NAMES[j] {
        "depth_agree" | "views_agree" | "overlap" | "inlier_coverage" | "inlier_ratio" => {
            logit(v[j])
        }
        "free_space_violation" | "views_violation" => log(v[j]),
        "gray_correlation" | "views_gray" | "local_gray" | "views_local_gray" => z(v[j]),
        _ => v[j],
    })
}

/// Where a pipeline's calibration came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CalibrationSource {
    /// The one shipped with the models (`models/calibration.json`, embedded).
    Shipped,
    /// The map's own ([`MapCalibration`]).
    Map,
    /// A file the user named (`--calibration`).
    File,
}

impl CalibrationSource {
    /// `shipped`, `map` or `file`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Shipped => "shipped",
            Self::Map => "map",
            Self::File => "file",
        }
    }
}

/// The `format` value of a map's own calibration ([`MapCalibration`]).
pub const MAP_FORMAT: &str = "pntr-map-calibration";
/// The map calibration version this build reads and writes.
pub const MAP_VERSION: u32 = 1;

/// A map's own calibration, stored in the map's header ([`crate::map::MapHeader::calibration`]):
/// the logistic model and the LOCALIZED threshold fitted on the map's own frames, each region of the
/// map held out in turn (`pntr_mapping::selfcal`), with what it was fitted on and what it measured there.
///
/// Versioned and checksummed on its own (FNV-1a of the canonical JSON of every other field, like a
/// calibration file), so a damaged or hand-edited one is refused when the map is read, whatever the
/// section checksum says. `fingerprint` names the map images it was fitted for: a map extended or
/// merged since then keeps it but reports it stale ([`MapCalibration::is_stale_for`]) until
/// `pntr calibrate --db` refits it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapCalibration {
    /// Always [`MAP_FORMAT`].
    pub format: String,
    /// Always [`MAP_VERSION`].
    pub version: u32,
    /// The model and threshold in use (the base's weights when only the threshold was refitted).
    pub calibration: Calibration,
    /// What was refitted: `threshold` (the base calibration's weights kept).
    pub method: String,
    /// The base calibration's threshold and checksum (the shipped one unless `--calibration`).
    pub base_threshold: f64,
    /// See `base_threshold`.
    pub base_checksum: String,
    /// Regions the map was cut into; each was held out once.
    pub regions: usize,
    /// Frames localized against the whole map (in-map).
    pub in_map_queries: usize,
    /// Frames localized with their own region held out.
    pub held_out_queries: usize,
    /// Of those, answered right (within 1 m, 10 deg) by the rest of the map (views into a kept
    /// region): they count as right, not as negatives.
    pub held_out_right: usize,
    /// Answers that are not right (every held-out frame the rest of the map cannot place, and
    /// in-map answers off by more than 1 m or 10 deg): the map's own negatives.
    pub negatives: usize,
    /// Negatives LOCALIZED at the base threshold.
    pub false_positives_base: usize,
    /// Negatives LOCALIZED at the map's threshold.
    pub false_positives: usize,
    /// Share of in-map frames LOCALIZED right at the base threshold.
    pub in_map_recall_base: f64,
    /// The same at the map's threshold.
    pub in_map_recall: f64,
    /// Precision (within 1 m, 10 deg) of every LOCALIZED answer of both passes at the map's
    /// threshold: what the map expects of itself.
    pub expected_precision: f64,
    /// Map images when it was fitted.
    pub images: usize,
    /// FNV-1a (hex) of the map's image ids in order when it was fitted ([`image_fingerprint`]).
    pub fingerprint: String,
    /// FNV-1a (hex) of every other field.
    #[serde(default)]
    pub checksum: String,
}

/// FNV-1a (hex) of image ids in order: which images a [`MapCalibration`] was fitted for.
pub fn image_fingerprint<'a>(ids: impl IntoIterator<Item = &'a str>) -> String {
    let mut h = pntr_core::bytes::FNV1A_START;
    for id in ids {
        h = pntr_core::bytes::fnv1a_update(h, id.as_bytes());
        h = pntr_core::bytes::fnv1a_update(h, &[0]);
    }
    format!("{h:016x}")
}

impl MapCalibration {
    /// The checksum of every field but `checksum`.
    pub fn compute_checksum(&self) -> String {
        let mut c = self.clone();
        c.checksum.clear();
        let bytes = serde_json::to_vec(&c).expect("plain data serialises");
        format!("{:016x}", pntr_core::bytes::fnv1a(&bytes))
    }

    /// With its own and its model's checksums filled in.
    pub fn sealed(mut self) -> Self {
        self.calibration.checksum = self.calibration.compute_checksum();
        self.checksum = self.compute_checksum();
        self
    }

    /// Check format, version, both checksums and the model (as [`Calibration::parse`] does); `path`
    /// names the map in errors.
    pub fn check(&self, path: &Path) -> Result<(), PipelineError> {
        let bad = |m: String| bad(path, format!("the map's own calibration: {m}"));
        if self.format != MAP_FORMAT || self.version != MAP_VERSION {
            return Err(bad(format!(
                "format `{}` version {}; this build reads `{MAP_FORMAT}` version {MAP_VERSION} (refit it with `pntr calibrate --db`)",
                self.format, self.version
            )));
        }
        if self.checksum != self.compute_checksum() {
            return Err(bad(
                "checksum mismatch (the map was changed or damaged; refit with `pntr calibrate --db`)"
                    .into(),
            ));
        }
        let text = serde_json::to_string(&self.calibration).map_err(|e| bad(e.to_string()))?;
        Calibration::parse(&text, path).map_err(|e| bad(e.to_string()))?;
        Ok(())
    }

    /// True when `ids` (the map's image ids in order) are not the images it was fitted for.
    pub fn is_stale_for<'a>(&self, ids: impl IntoIterator<Item = &'a str>) -> bool {
        image_fingerprint(ids) != self.fingerprint
    }
}

/// Number of model inputs.
pub const N_FEATURES: usize = EVIDENCE_NAMES.len();

/// A disagreeing rival with at least this share of a candidate's inliers counts with its whole
/// probability in [`choose`]; one with fewer counts in proportion (a quarter of the inliers: half).
/// Measured (BENCHMARKS.md, "Rivals weighed by their inliers"): from the shipped threshold up, the
/// same wrong answers and more right ones than counting every rival whole.
pub const RIVAL_FULL_INLIER_SHARE: f64 = 0.5;

/// The answer's confidence from each candidate's probability `probabilities[i]` and registration
/// inliers `inliers[i]` (parallel slices): `p_i * (1 - max_j w_ij p_j)` over its disagreeing rivals
/// `rivals[i]`, the chance that candidate i is right and its strongest rival is not (they cannot both
/// be right), where `w_ij = min(1, inliers_j / (RIVAL_FULL_INLIER_SHARE * inliers_i))`: a rival held
/// by a small fraction of candidate i's matches (a room's symmetry met by a few wall-texture matches)
/// is weaker evidence that the place is ambiguous. Returns (index of the most confident candidate,
/// its confidence), `None` without candidates.
pub fn choose(
    probabilities: &[f64],
    inliers: &[usize],
    rivals: &[Vec<usize>],
) -> Option<(usize, f64)> {
    debug_assert_eq!(inliers.len(), probabilities.len(), "parallel slices");
    let count = |i: usize| inliers.get(i).copied().unwrap_or(0) as f64;
    (0..probabilities.len())
        .map(|i| {
            let own = count(i).max(1.0);
            let rival = rivals
                .get(i)
                .into_iter()
                .flatten()
                .map(|&j| {
                    let weight = (count(j) / (RIVAL_FULL_INLIER_SHARE * own)).min(1.0);
                    weight * probabilities[j]
                })
                .fold(0.0, f64::max);
            (i, probabilities[i] * (1.0 - rival))
        })
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The logistic function 1 / (1 + e^-z).
pub fn sigmoid(z: f64) -> f64 {
    1.0 / (1.0 + (-z).exp())
}

/// One bin of a reliability diagram.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Bin {
    /// Lower edge of the bin's probability range.
    pub lo: f64,
    /// Upper edge.
    pub hi: f64,
    /// Answers in the bin.
    pub count: usize,
    /// Their mean predicted probability.
    pub mean_confidence: f64,
    /// The share of them that were right.
    pub accuracy: f64,
}

/// Expected calibration error over `bins` equal-width bins (the count-weighted mean gap between
/// predicted probability and observed accuracy; Naeini et al., 2015), and the bins.
pub fn ece(probs: &[(f64, bool)], bins: usize) -> (f64, Vec<Bin>) {
    let mut out: Vec<Bin> = (0..bins)
        .map(|i| Bin {
            lo: i as f64 / bins as f64,
            hi: (i + 1) as f64 / bins as f64,
            ..Bin::default()
        })
        .collect();
    for &(p, right) in probs {
        let b = ((p * bins as f64) as usize).min(bins - 1);
        out[b].count += 1;
        out[b].mean_confidence += p;
        out[b].accuracy += right as u8 as f64;
    }
    let mut e = 0.0;
    for b in &mut out {
        if b.count > 0 {
            b.mean_confidence /= b.count as f64;
            b.accuracy /= b.count as f64;
            e += b.count as f64 * (b.mean_confidence - b.accuracy).abs();
        }
    }
    (e / probs.len().max(1) as f64, out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_calibration_is_valid() {
        let c = Calibration::embedded();
        assert!(c.threshold >= 0.5);
        assert_eq!(c.features.len(), EVIDENCE_NAMES.len());
    }

    #[test]
    fn ece_of_a_perfect_and_a_wrong_model() {
        let perfect: Vec<(f64, bool)> = (0..100)
            .map(|i| (0.0 + (i % 2) as f64, i % 2 == 1))
            .collect();
        assert!(ece(&perfect, 10).0 < 1e-12);
        let wrong: Vec<(f64, bool)> = (0..100).map(|i| (0.95, i < 50)).collect();
        assert!((ece(&wrong, 10).0 - 0.45).abs() < 1e-9);
    }

    #[test]
    fn a_rival_with_a_fraction_of_the_inliers_counts_in_proportion() {
        let rivals = [vec![1], vec![0]];
        // 200 inliers against a rival pose of 20 (a symmetric wall's texture): the rival counts
        // with 20 / (0.5 * 200) = 0.2 of its probability.
        let (i, conf) = choose(&[0.99, 0.6], &[200, 20], &rivals).unwrap();
        assert_eq!(i, 0);
        assert!((conf - 0.99 * (1.0 - 0.2 * 0.6)).abs() < 1e-12, "{conf}");
        // A rival with half the inliers or more counts whole, and the weaker candidate always meets
        // its stronger rival whole.
        let (_, conf) = choose(&[0.99, 0.6], &[200, 100], &rivals).unwrap();
        assert!((conf - 0.99 * 0.4).abs() < 1e-12, "{conf}");
        let (i, conf) = choose(&[0.6, 0.99], &[20, 200], &rivals).unwrap();
        assert_eq!(i, 1);
        assert!((conf - 0.99 * (1.0 - 0.2 * 0.6)).abs() < 1e-12, "{conf}");
        // No candidates, no answer; one without rivals keeps its probability.
        assert!(choose(&[], &[], &[]).is_none());
        assert_eq!(choose(&[0.7], &[15], &[vec![]]), Some((0, 0.7)));
    }
}
