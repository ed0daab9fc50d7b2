//! Finding a shared library set-up installed under `.deps/` (ONNX Runtime, OpenVINO).

use std::path::{Path, PathBuf};

/// The places a library is looked for, in order: `explicit`, the file the environment variable `env`
/// names, then `.deps/<dir>/<file>` in every folder above the executable and above the current
/// directory (so binaries of a checkout, tests and installs next to a checkout find set-up's copy).
pub fn candidates(explicit: Option<&Path>, env: &str, dir: &str, file: &str) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = explicit.map(Path::to_path_buf).into_iter().collect();
    if let Some(p) = std::env::var_os(env) {
        out.push(PathBuf::from(p));
    }
    let rel = Path::new(".deps").join(dir).join(file);
    if let Ok(exe) = std::env::current_exe() {
        out.extend(exe.ancestors().skip(1).map(|d| d.join(&rel)));
    }
    if let Ok(cwd) = std::env::current_dir() {
        out.extend(cwd.ancestors().map(|d| d.join(&rel)));
    }
    out
}

/// The first of `tried` that is a file. Errors: none is; the message says to run set-up or set
/// `env`, and names the first four places looked at.
pub fn first_file<'a>(tried: &'a [PathBuf], env: &str) -> Result<&'a PathBuf, String> {
    tried.iter().find(|p| p.is_file()).ok_or_else(|| {
        format!(
            "library not found (run scripts/setup.sh or set {env}); looked at {}",
            tried
                .iter()
                .take(4)
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )
    })
}
