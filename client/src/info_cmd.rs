//! `pntr info --db`: what a map file holds (its header, calibration, sessions; `--images` every
//! image's id and pose).

use std::path::Path;

use anyhow::{Context, Result};
use pntr_pipeline::calibration::Calibration;
use pntr_pipeline::mapfile;

use crate::loading::load_map;

/// Every image of the map at `path`: id, place, stamp (seconds or null) and `world_from_camera`
/// (translation, rotation w x y z with w >= 0) in the map's frame and camera axes.
/// Also the map's version (build time and content checksum), which needs the whole file.
fn image_list(path: &Path) -> Result<(Vec<serde_json::Value>, String)> {
    let map = load_map(path, 1).with_context(|| format!("loading {}", path.display()))?;
    let version = pntr_service::engine::MapVersion::of(&map).label;
    let list = map
        .images
        .iter()
        .map(|im| {
            let t = im.world_from_camera.translation.vector;
            let q = im.world_from_camera.rotation.quaternion();
            let s = if q.w < 0.0 { -1.0 } else { 1.0 };
            serde_json::json!({
                "id": im.id,
                "place": im.point,
                "stamp": im.stamp,
                "translation": [t.x, t.y, t.z],
                "rotation_wxyz": [s * q.w, s * q.i, s * q.j, s * q.k],
            })
        })
        .collect();
    Ok((list, version))
}

/// `pntr info --db FILE [--images]`: what a map file says about itself, from its header and its
/// images' ids (fast on maps of any size; the ids say whether the map's own calibration is stale),
/// and with `images` every image's id, place, stamp and pose. Errors name the file and what is
/// wrong with it.
pub fn info(path: &Path, as_json: bool, images: bool) -> Result<()> {
    let header = mapfile::read_header(path)?;
    let list = if images {
        Some(image_list(path)?)
    } else {
        None
    };
    // Whether the map changed since its own calibration was fitted shows in its image ids (read
    // from the records' starts: fast on maps of any size).
    let stale = match &header.calibration {
        Some(c) => c.is_stale_for(mapfile::read_image_ids(path)?.iter().map(String::as_str)),
        None => false,
    };
    if as_json {
        let mut v = serde_json::to_value(&header)?;
        // `calibration.source`, `.stale` and `.threshold`, as `pntr info --addr --json` says them.
        let (calibration, source, threshold) = match &header.calibration {
            Some(own) => (v["calibration"].clone(), "map", own.calibration.threshold),
            None => (
                crate::own_calibration::summary(None, false),
                "shipped",
                Calibration::embedded().threshold,
            ),
        };
        if let (Some(o), serde_json::Value::Object(mut c)) = (v.as_object_mut(), calibration) {
            c.insert("source".into(), source.into());
            c.insert("stale".into(), stale.into());
            c.insert("threshold".into(), threshold.into());
            o.insert("calibration".into(), c.into());
        }
        if let (Some(o), Some((list, version))) = (v.as_object_mut(), list) {
            o.insert("image_list".into(), list.into());
            o.insert("version".into(), version.into());
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let p = &header.preset;
    println!(
        "map {} ({}), built by {} in {:.1} s",
        header.map_id,
        path.display(),
        header.built_by,
        header.build_seconds
    );
    let keypoints = if p.extractor_top_k() > p.keypoints {
        format!(
            "{} keypoints (up to {} on larger images)",
            p.keypoints,
            p.extractor_top_k()
        )
    } else {
        format!("{} keypoints", p.keypoints)
    };
    println!(
        "preset {}: {} ({} words) + {}, index {}, {keypoints}, {} candidates, matcher {}, solver {:?}",
        p.name, p.global, p.vlad_words, p.extractor, p.index, p.candidates, p.matcher, p.solver
    );
    if p.map_extractor() != p.extractor {
        println!(
            "map images described by {}, queries by {}",
            p.map_extractor(),
            p.extractor
        );
    }
    for m in &header.models {
        println!(
            "model {}: {} ({}, checksum {})",
            m.role,
            m.name,
            m.file.as_deref().unwrap_or("no file"),
            m.checksum.as_deref().unwrap_or("-")
        );
    }
    let k = &header.intrinsics;
    println!(
        "camera (first image): fx {:.2} fy {:.2} cx {:.2} cy {:.2}, axes {}",
        k.fx, k.fy, k.cx, k.cy, header.camera_axes
    );
    println!(
        "scenes ({}): {}; world up axis {}",
        header.scenes.len(),
        header.scenes.join(", "),
        header.up_axis
    );
    if let Some(at) = header.built_at_unix_s.filter(|s| s.is_finite()) {
        let when = time::OffsetDateTime::from_unix_timestamp(at.floor() as i64)
            .ok()
            .and_then(|t| {
                t.format(&time::format_description::well_known::Rfc3339)
                    .ok()
            })
            .unwrap_or_else(|| format!("{at:.0} s since the Unix epoch"));
        println!("built (or last extended) at {when}");
    }
    for r in &header.sessions {
        println!(
            "session {}: {} frames, stamps {:.3} .. {:.3} s",
            r.name, r.frames, r.first_stamp, r.last_stamp
        );
    }
    println!(
        "{}",
        crate::own_calibration::line(header.calibration.as_ref(), stale)
    );
    if let Some((_, version)) = &list {
        println!("version {version}");
    }
    for im in list.iter().flat_map(|(l, _)| l) {
        println!(
            "{} place {} stamp {} t {} q(wxyz) {}",
            im["id"].as_str().unwrap_or(""),
            im["place"],
            im["stamp"],
            im["translation"],
            im["rotation_wxyz"]
        );
    }
    Ok(())
}
