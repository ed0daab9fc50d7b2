//! Fitting a confidence calibration ([`pntr_pipeline::calibration::Calibration`]): a logistic model
//! on labelled candidates by Newton's method, its threshold chosen for a target precision, and the
//! refit of a base calibration towards a map's own answers. What `pntr calibrate` runs and what a
//! map's own calibration ([`crate::selfcal::fit`]) starts from; applying a calibration (the
//! probability of an answer, the choice among candidates) is the pipeline's.

use pntr_pipeline::calibration::{
    choose, ece, model_inputs, sigmoid, Calibration, FitInfo, FORMAT, N_FEATURES, VERSION,
};
use pntr_pipeline::pipeline::{Pipeline, Query};
use pntr_pipeline::verify::{Evidence, EVIDENCE_NAMES};
use pntr_pipeline::PipelineError;
use pntr_synth::effects::RobotEffects;
use serde::Serialize;

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

/// The verified candidates of one query, for fitting: each candidate's evidence and label, and for
/// each the indices of the candidates whose pose disagrees with it (its rivals).
#[derive(Debug, Clone, Default)]
pub struct QuerySamples {
    /// (evidence, right within (1 m, 10 deg)) per candidate.
    pub candidates: Vec<(Evidence, bool)>,
    /// `rivals[i]`: candidates whose pose disagrees with candidate i (0.5 m, 10 deg).
    pub rivals: Vec<Vec<usize>>,
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

/// One verified candidate of a query [`labelled_samples`] localized: what `pntr calibrate
/// --samples` writes, one JSON line each, to study which candidates the fit sees.
#[derive(Debug, Clone, Serialize)]
pub struct CandidateNote {
    /// The query (Point file and index).
    pub query: String,
    /// Whether the robot camera's effects were applied to it.
    pub effects: bool,
    /// The candidate's map image.
    pub image: String,
    /// Whether it is the one the answer chose.
    pub chosen: bool,
    /// Its pose's position error against the query's truth, metres.
    pub error_m: f64,
    /// Its pose's geodesic rotation error, degrees.
    pub error_deg: f64,
    /// Its own probability of being right.
    pub confidence: f64,
    /// The answer's confidence.
    pub answer_confidence: f64,
    /// The map images of its rivals (candidates whose poses disagree with it).
    pub rivals: Vec<String>,
}

/// Localize every query of `list` ((Point file, query index) of a dataset, its poses in Habitat
/// axes) against `pipeline`'s map, with a robot camera's `effects` when given (seeded by the
/// query's place in the list), and label each verified candidate as the map's own calibration does
/// (right within (1 m, 10 deg) of the truth; never when `negative`: the query's place is not in
/// the map). Each query's samples go to `out` (when it has a candidate), each candidate's note to
/// `notes`. A query the pipeline fails on is passed over with a warning. `progress(done, total)`
/// after each query. Errors: a query that cannot be read.
pub fn labelled_samples(
    pipeline: &Pipeline,
    list: &[(pntr_dataset::PointEntry, usize)],
    effects: Option<&RobotEffects>,
    negative: bool,
    out: &mut Vec<QuerySamples>,
    notes: &mut Vec<CandidateNote>,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(), PipelineError> {
    let mut views = pntr_dataset::queries::QueryViews::default();
    for (i, (p, qi)) in list.iter().enumerate() {
        let v = views.view(p, *qi)?;
        let mut q = Query {
            rgb: v.rgb,
            depth: v.depth,
            intrinsics: v.intrinsics,
        };
        if let Some(fx) = effects {
            fx.apply(&mut q.rgb, &mut q.depth, i as u64 + 1);
        }
        let l = match pipeline.localize(&q) {
            Ok(l) => l,
            Err(e) => {
                tracing::warn!("query {}: {e}", p.query_id(*qi));
                continue;
            }
        };
        // The dataset's poses have Habitat camera axes; the candidates', the map's (a map built from
        // a recording has OpenCV axes).
        let truth = pntr_core::convert_axes(
            &v.world_from_camera,
            pntr_core::CameraAxes::Habitat,
            pipeline.map.header.axes(),
        );
        let group = crate::selfcal::samples_of(&l, (!negative).then_some(&truth));
        for c in &l.verified {
            notes.push(CandidateNote {
                query: p.query_id(*qi),
                effects: effects.is_some(),
                image: pipeline.map.images[c.image].id.clone(),
                chosen: l.image == Some(c.image),
                error_m: (c.pose.translation.vector - truth.translation.vector).norm(),
                error_deg: pntr_core::rotation_angle_deg(&c.pose.rotation, &truth.rotation),
                confidence: c.confidence,
                answer_confidence: l.confidence,
                rivals: c
                    .rivals
                    .iter()
                    .map(|&r| pipeline.map.images[r].id.clone())
                    .collect(),
            });
        }
        if !group.candidates.is_empty() {
            out.push(group);
        }
        progress(i + 1, list.len());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
