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
/// map held out in turn ([`crate::selfcal`]), with what it was fitted on and what it measured there.
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

/// Today's date (UTC) as YYYY-MM-DD.
pub fn today() -> String {
    let days = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() / 86_400)
        .unwrap_or(0) as i64;
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + (m <= 2) as i64;
    format!("{y:04}-{m:02}-{d:02}")
}

/// Number of model inputs.
pub const N_FEATURES: usize = EVIDENCE_NAMES.len();

/// The verified candidates of one query, for fitting: each candidate's evidence and label, and for
/// each the indices of the candidates whose pose disagrees with it (its rivals).
#[derive(Debug, Clone, Default)]
pub struct QuerySamples {
    /// (evidence, right within (1 m, 10 deg)) per candidate.
    pub candidates: Vec<(Evidence, bool)>,
    /// `rivals[i]`: candidates whose pose disagrees with candidate i (0.5 m, 10 deg).
    pub rivals: Vec<Vec<usize>>,
}

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

fn sigmoid(z: f64) -> f64 {
    1.0 / (1.0 + (-z).exp())
}

/// Fit a logistic model to every candidate of `queries` (evidence, right within (1 m, 10 deg)) by
/// Newton's method with an L2 penalty `l2` on the standardised weights; the threshold is the smallest
/// answer confidence ([`choose`]) at which the queries' answers reach `target_precision` (never below
/// 0.5). Out-of-map queries are queries whose candidates are all wrong.
pub fn fit(
    queries: &[QuerySamples],
    l2: f64,
    target_precision: f64,
    preset: &str,
) -> Result<Calibration, PipelineError> {
    let samples: Vec<(Evidence, bool)> = queries
        .iter()
        .flat_map(|q| q.candidates.iter().copied())
        .collect();
    let n = EVIDENCE_NAMES.len();
    let pos = samples.iter().filter(|s| s.1).count();
    if pos < 5 || samples.len() - pos < 5 {
        return Err(PipelineError::Config(format!(
            "calibration needs at least 5 right and 5 wrong answers; got {pos} right of {}",
            samples.len()
        )));
    }
    let xs: Vec<[f64; N_FEATURES]> = samples.iter().map(|s| model_inputs(&s.0)).collect();
    let m = samples.len() as f64;
    let mut mean = vec![0.0; n];
    let mut scale = vec![0.0; n];
    for x in &xs {
        for j in 0..n {
            mean[j] += x[j] / m;
        }
    }
    for x in &xs {
        for j in 0..n {
            scale[j] += (x[j] - mean[j]).powi(2) / m;
        }
    }
    for s in &mut scale {
        *s = s.sqrt().max(1e-6);
    }
    let z: Vec<Vec<f64>> = xs
        .iter()
        .map(|x| {
            let mut v: Vec<f64> = (0..n).map(|j| (x[j] - mean[j]) / scale[j]).collect();
            v.push(1.0);
            v
        })
        .collect();
    let y: Vec<f64> = samples.iter().map(|s| s.1 as u8 as f64).collect();
    let d = n + 1;
    let mut w = nalgebra::DVector::<f64>::zeros(d);
    for _ in 0..50 {
        let mut g = nalgebra::DVector::<f64>::zeros(d);
        let mut h = nalgebra::DMatrix::<f64>::zeros(d, d);
        for (zi, &yi) in z.iter().zip(&y) {
            let zi = nalgebra::DVector::from_column_slice(zi);
            let p = sigmoid(w.dot(&zi));
            g += &zi * (p - yi);
            h += &zi * zi.transpose() * (p * (1.0 - p)).max(1e-9);
        }
        for j in 0..n {
            g[j] += l2 * w[j];
            h[(j, j)] += l2;
        }
        let Some(step) = h.lu().solve(&g) else { break };
        w -= &step;
        if step.norm() < 1e-9 {
            break;
        }
    }
    let mut c = Calibration {
        format: FORMAT.into(),
        version: VERSION,
        features: EVIDENCE_NAMES.iter().map(|s| s.to_string()).collect(),
        mean,
        scale,
        weights: w.as_slice()[..n].to_vec(),
        bias: w[n],
        threshold: 0.5,
        preset: preset.into(),
        fitted_on: FitInfo::default(),
        checksum: String::new(),
    };
    let probs: Vec<(f64, bool)> = queries
        .iter()
        .filter_map(|q| {
            let p: Vec<f64> = q.candidates.iter().map(|s| c.probability(&s.0)).collect();
            let inliers: Vec<usize> = q.candidates.iter().map(|s| s.0.inliers()).collect();
            let (i, conf) = choose(&p, &inliers, &q.rivals)?;
            Some((conf, q.candidates[i].1))
        })
        .collect();
    let pos = probs.iter().filter(|p| p.1).count();
    c.threshold = threshold_for_precision(&probs, target_precision).max(0.5);
    let kept: Vec<&(f64, bool)> = probs.iter().filter(|p| p.0 >= c.threshold).collect();
    c.fitted_on = FitInfo {
        samples: samples.len(),
        positives: samples.iter().filter(|s| s.1).count(),
        queries: queries.len(),
        ece: ece(&probs, 10).0,
        precision_at_threshold: kept.iter().filter(|p| p.1).count() as f64
            / kept.len().max(1) as f64,
        recall_at_threshold: kept.iter().filter(|p| p.1).count() as f64 / pos.max(1) as f64,
        ..FitInfo::default()
    };
    Ok(c)
}

/// Refit `base`'s weights and bias on `queries`' candidates, keeping its standardisation (mean and
/// scale) and pulling each weight towards `base`'s by an L2 penalty `l2` on the difference (the
/// bias is free): with few samples the result stays near `base`, with many it follows them. Newton's
/// method, as [`fit`]. The threshold and provenance stay `base`'s (the caller sets them).
pub fn refit_toward(base: &Calibration, queries: &[QuerySamples], l2: f64) -> Calibration {
    let n = N_FEATURES;
    let z: Vec<(nalgebra::DVector<f64>, f64)> = queries
        .iter()
        .flat_map(|q| q.candidates.iter())
        .map(|(e, right)| {
            let x = model_inputs(e);
            let mut v = nalgebra::DVector::<f64>::zeros(n + 1);
            for j in 0..n {
                v[j] = (x[j] - base.mean[j]) / base.scale[j];
            }
            v[n] = 1.0;
            (v, *right as u8 as f64)
        })
        .collect();
    let mut w = nalgebra::DVector::<f64>::zeros(n + 1);
    for j in 0..n {
        w[j] = base.weights[j];
    }
    w[n] = base.bias;
    for _ in 0..50 {
        let mut g = nalgebra::DVector::<f64>::zeros(n + 1);
        let mut h = nalgebra::DMatrix::<f64>::zeros(n + 1, n + 1);
        for (zi, yi) in &z {
            let p = sigmoid(w.dot(zi));
            g += zi * (p - yi);
            h += zi * zi.transpose() * (p * (1.0 - p)).max(1e-9);
        }
        for j in 0..n {
            g[j] += l2 * (w[j] - base.weights[j]);
            h[(j, j)] += l2;
        }
        // A bias with nothing to pull it (all samples one label) stays put.
        h[(n, n)] += 1e-6;
        let Some(step) = h.lu().solve(&g) else { break };
        w -= &step;
        if step.norm() < 1e-9 {
            break;
        }
    }
    Calibration {
        weights: w.as_slice()[..n].to_vec(),
        bias: w[n],
        checksum: String::new(),
        ..base.clone()
    }
}

/// The smallest threshold at which the answers kept (probability >= threshold) reach `target`
/// precision, scanning from the top; 1.0 when no threshold does.
pub fn threshold_for_precision(probs: &[(f64, bool)], target: f64) -> f64 {
    let mut sorted: Vec<(f64, bool)> = probs.to_vec();
    sorted.sort_by(|a, b| b.0.total_cmp(&a.0));
    let (mut tp, mut best) = (0usize, 1.0);
    for (i, &(p, right)) in sorted.iter().enumerate() {
        tp += right as usize;
        let next_differs = sorted.get(i + 1).is_none_or(|n| n.0 < p);
        if next_differs && tp as f64 / (i + 1) as f64 >= target {
            best = p;
        }
    }
    best
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
    fn fit_saves_loads_and_refuses_damage() {
        // Right answers agree densely; wrong ones do not (with overlap, so the fit is not separable).
        let queries: Vec<QuerySamples> = (0..400)
            .map(|i| {
                let right = i % 3 != 0;
                let x = (i % 17) as f64 / 17.0;
                let e = Evidence {
                    depth_agree: if right { 0.6 + 0.4 * x } else { 0.9 * x },
                    views_agree: if right { 0.7 + 0.3 * x } else { x },
                    log_inliers: if right { 3.0 + x } else { 2.5 + x },
                    ..Evidence::default()
                };
                QuerySamples {
                    candidates: vec![(e, right)],
                    rivals: vec![vec![]],
                }
            })
            .collect();
        let c = fit(&queries, 1.0, 0.99, "xfeat-mnn").unwrap();
        let good = Evidence {
            depth_agree: 0.98,
            views_agree: 0.98,
            log_inliers: 4.0,
            ..Evidence::default()
        };
        let bad = Evidence {
            depth_agree: 0.2,
            views_agree: 0.2,
            log_inliers: 2.6,
            ..Evidence::default()
        };
        assert!(c.probability(&good) > 0.9 && c.probability(&bad) < 0.1);
        assert!(c.fitted_on.precision_at_threshold >= 0.99);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cal.json");
        c.save(&path).unwrap();
        let back = Calibration::load(&path).unwrap();
        assert_eq!(back.weights, c.weights);
        assert_eq!(back.probability(&good), c.probability(&good));
        let text = std::fs::read_to_string(&path).unwrap();
        let damaged = text.replacen("\"threshold\": 0.", "\"threshold\": 0.9", 1);
        assert_ne!(damaged, text);
        std::fs::write(&path, damaged).unwrap();
        let e = Calibration::load(&path).unwrap_err().to_string();
        assert!(e.contains("cal.json") && e.contains("checksum"), "{e}");
        std::fs::write(&path, &text[..text.len() / 3]).unwrap();
        assert!(Calibration::load(&path).is_err());
        // Rivals: a strong disagreeing rival lowers the answer's confidence.
        let (i, conf) = choose(&[0.9, 0.8], &[40, 30], &[vec![1], vec![0]]).unwrap();
        assert_eq!(i, 0);
        assert!((conf - 0.9 * 0.2).abs() < 1e-12);
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

    #[test]
    fn threshold_reaches_the_target_precision() {
        let probs = vec![
            (0.99, true),
            (0.9, true),
            (0.8, false),
            (0.7, true),
            (0.2, false),
        ];
        assert_eq!(threshold_for_precision(&probs, 1.0), 0.9);
        assert_eq!(threshold_for_precision(&probs, 0.75), 0.7);
    }
}
