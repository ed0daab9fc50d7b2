//! What the commands write: JSON and text files (to a temporary name, then renamed), and progress
//! bars on stderr, including the ones a mapping job's progress ([`pntr_mapping::progress`]) turns
//! into.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use pntr_mapping::progress::Step;

/// A progress bar on stderr for `total` items, saying `what`.
pub fn bar(total: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} ({per_sec}, eta {eta})")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// Write `value` as pretty JSON to `path` atomically.
pub fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<()> {
    write_text(path, &serde_json::to_string_pretty(value)?)
}

/// Write `text` to `path` atomically.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    let tmp = PathBuf::from(format!("{}.partial-{}", path.display(), std::process::id()));
    let written = std::fs::write(&tmp, text)
        .with_context(|| format!("writing {}", tmp.display()))
        .and_then(|()| {
            std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
        });
    if written.is_err() {
        // A full disk: no half-written file left beside the one asked for.
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// A progress bar cleared when dropped.
pub struct Bar(pub ProgressBar);

impl Drop for Bar {
    fn drop(&mut self) {
        self.0.finish_and_clear();
    }
}

/// A mapping job's progress as bars on stderr: one bar per stage, cleared when the next starts or
/// when the callback is dropped.
pub fn bars() -> impl FnMut(Step<'_>) {
    let mut shown: Option<(String, Bar)> = None;
    move |s: Step<'_>| {
        if shown.as_ref().is_none_or(|(stage, _)| stage != s.stage) {
            shown = Some((s.stage.to_string(), Bar(bar(s.total, s.stage))));
        }
        if let Some((_, pb)) = &shown {
            pb.0.set_length(s.total as u64);
            pb.0.set_position(s.done as u64);
        }
    }
}
