//! What the command line says about a map's own calibration (`build-db`, `calibrate --db`, `info`,
//! `maps merge`): its summary in JSON, one line for people, and the fit's labelled answers as JSON
//! lines. The fitting itself is [`pntr_mapping::own_calibration`].

use std::path::Path;

use anyhow::Result;
use pntr_mapping::selfcal::Answered;
use pntr_pipeline::calibration::{Calibration, MapCalibration};

/// One JSON line per frame: `{"held_out", "region", "candidates": [{"right", "evidence"}],
/// "rivals"}`.
pub fn write_samples(path: &Path, answers: &[Answered]) -> Result<()> {
    let mut text = String::new();
    for a in answers {
        let line = serde_json::json!({
            "held_out": a.held_out,
            "region": a.region,
            "candidates": a.samples.candidates.iter().map(|(e, right)| serde_json::json!({"right": right, "evidence": e})).collect::<Vec<_>>(),
            "rivals": a.samples.rivals,
        });
        text += &format!("{line}\n");
    }
    crate::output::write_text(path, &text)
}

/// What `build-db --json`, `calibrate` and `info` say about a map's calibration: its source, the
/// threshold, what it was fitted on, what it measured and whether it is stale.
pub fn summary(map_calibration: Option<&MapCalibration>, stale: bool) -> serde_json::Value {
    match map_calibration {
        None => serde_json::json!({
            "source": "shipped",
            "threshold": Calibration::embedded().threshold,
            "fitted_on": Calibration::embedded().fitted_on.datasets,
        }),
        Some(c) => serde_json::json!({
            "source": "map",
            "method": c.method,
            "threshold": c.calibration.threshold,
            "base_threshold": c.base_threshold,
            "fitted_on": c.calibration.fitted_on.datasets,
            "date": c.calibration.fitted_on.date,
            "regions": c.regions,
            "in_map_frames": c.in_map_queries,
            "held_out_frames": c.held_out_queries,
            "held_out_right": c.held_out_right,
            "negatives": c.negatives,
            "false_positives_at_base_threshold": c.false_positives_base,
            "false_positives": c.false_positives,
            "in_map_recall_at_base_threshold": c.in_map_recall_base,
            "in_map_recall": c.in_map_recall,
            "expected_precision": c.expected_precision,
            "stale": stale,
        }),
    }
}

/// One line for people: where the calibration comes from and what it measured.
pub fn line(map_calibration: Option<&MapCalibration>, stale: bool) -> String {
    match map_calibration {
        None => format!(
            "calibration: shipped (threshold {:.3})",
            Calibration::embedded().threshold
        ),
        Some(c) => format!(
            "calibration: the map's own{} (threshold {:.3}, shipped {:.3}; {} regions held out, {} of {} own negatives LOCALIZED, {} at the shipped threshold; in-map recall {:.3}, {:.3} at the shipped threshold; expected precision {:.3})",
            if stale {
                ", STALE: the map changed since it was fitted (refit with `pntr calibrate --db`)"
            } else {
                ""
            },
            c.calibration.threshold,
            c.base_threshold,
            c.regions,
            c.false_positives,
            c.negatives,
            c.false_positives_base,
            c.in_map_recall,
            c.in_map_recall_base,
            c.expected_precision
        ),
    }
}
