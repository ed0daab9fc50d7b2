//! Where the ONNX models are: the same answer for `pntr`, `pntr-server`, an installed binary, a
//! container and a systemd unit, whatever the working directory.
//!
//! Order: an explicit folder (`--models`, the config file), `PNTR_MODELS`, `./models`, `models` next
//! to the executable, the install prefix's `../share/pntr/models` beside the executable's folder, and
//! the source tree's `models` above a cargo build's `target/<profile>/` (and the source tree this
//! binary was built from). Among those, the first holding [`MARKER`] wins, else the first holding any
//! `.onnx` file (a folder with only other presets' models), else the first that exists. An explicit
//! folder or `PNTR_MODELS` is used as given when it exists (a missing one is an error, not a reason to
//! look elsewhere); when nothing is found the error lists every place looked at.

use std::path::{Path, PathBuf};

/// The file whose presence marks a models folder (the default extractor's network).
pub const MARKER: &str = "xfeat_backbone.onnx";

/// The environment variable naming the models folder.
pub const ENV: &str = "PNTR_MODELS";

/// The folders looked at, in order, when nothing is given explicitly.
pub fn candidates() -> Vec<PathBuf> {
    let mut out = vec![PathBuf::from("models")];
    if let Ok(exe) = std::env::current_exe() {
        let exe = exe.canonicalize().unwrap_or(exe);
        if let Some(dir) = exe.parent() {
            out.push(dir.join("models"));
            out.push(dir.join("../share/pntr/models"));
            // target/<profile>/pntr -> the workspace's models/.
            out.push(dir.join("../../models"));
        }
    }
    // The source tree this binary was built from (another CARGO_TARGET_DIR or --target layout).
    out.push(PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../models"
    )));
    out
}

fn has_onnx(dir: &Path) -> bool {
    std::fs::read_dir(dir).is_ok_and(|entries| {
        entries
            .filter_map(Result::ok)
            .any(|e| e.path().extension().is_some_and(|x| x == "onnx"))
    })
}

/// The models folder: `explicit` if given, else `PNTR_MODELS`, else the first of [`candidates`]
/// holding [`MARKER`]. Errors name the folder that lacks the models, or every place looked at.
pub fn locate(explicit: Option<&Path>) -> Result<PathBuf, String> {
    let given = explicit
        .map(|p| (p.to_path_buf(), "--models"))
        .or_else(|| std::env::var_os(ENV).map(|p| (PathBuf::from(p), ENV)));
    if let Some((dir, from)) = given {
        if dir.is_dir() {
            return Ok(dir);
        }
        return Err(format!(
            "{from} {}: no such folder (the folder of the ONNX models, `models/` in the source tree)",
            dir.display()
        ));
    }
    let tried = candidates();
    let found = tried
        .iter()
        .find(|d| d.join(MARKER).is_file())
        .or_else(|| tried.iter().find(|d| has_onnx(d)))
        .or_else(|| tried.iter().find(|d| d.is_dir()));
    if let Some(found) = found {
        return Ok(found.clone());
    }
    Err(format!(
        "the ONNX models ({MARKER} and the others) were not found; looked in {} (give --models DIR or set {ENV})",
        tried
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn explicit_folders_are_checked_and_named() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nope");
        let e = locate(Some(&missing)).unwrap_err();
        assert!(
            e.contains("--models") && e.contains("no such folder"),
            "{e}"
        );
        // An existing folder is used as given (it may hold only another preset's models).
        assert_eq!(locate(Some(dir.path())).unwrap(), dir.path());
        assert!(candidates()
            .iter()
            .any(|p| p.ends_with("share/pntr/models")));
    }
}
