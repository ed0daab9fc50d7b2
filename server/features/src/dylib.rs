//! Finding a shared library set-up installed under `.deps/` (ONNX Runtime, OpenVINO).

use std::path::{Path, PathBuf};

/// The places a library is looked for, in order: `explicit`, the file the environment variable `env`
/// names, then `.deps/<dir>/<file>` in every folder above the executable, above the checkout the
/// binary was built from (a `CARGO_TARGET_DIR` elsewhere) and above the current directory (so
/// binaries of a checkout, tests and installs next to a checkout find set-up's copy).
/// Errors: `env` names something that is not a file (a typo there is not passed over for another
/// copy); an empty `env` counts as unset.
pub fn candidates(
    explicit: Option<&Path>,
    env: &str,
    dir: &str,
    file: &str,
) -> Result<Vec<PathBuf>, String> {
    let mut out: Vec<PathBuf> = explicit.map(Path::to_path_buf).into_iter().collect();
    if let Some(p) = std::env::var_os(env).filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        if !p.is_file() {
            return Err(format!(
                "{env} names {}, which is not a file (it should name {file})",
                p.display()
            ));
        }
        out.push(p);
    }
    let rel = Path::new(".deps").join(dir).join(file);
    if let Ok(exe) = std::env::current_exe() {
        out.extend(exe.ancestors().skip(1).map(|d| d.join(&rel)));
    }
    out.extend(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .ancestors()
            .map(|d| d.join(&rel)),
    );
    if let Ok(cwd) = std::env::current_dir() {
        out.extend(cwd.ancestors().map(|d| d.join(&rel)));
    }
    let mut seen = std::collections::HashSet::new();
    out.retain(|p| seen.insert(p.clone()));
    Ok(out)
}

/// The first of `tried` that is a file. Errors: none is; the message says to run set-up (in a
/// checkout) or set `env`, and names the first six places looked at.
pub fn first_file<'a>(tried: &'a [PathBuf], env: &str) -> Result<&'a PathBuf, String> {
    tried.iter().find(|p| p.is_file()).ok_or_else(|| {
        format!(
            "library not found (in a checkout run scripts/setup.sh; elsewhere set {env} to the \
             library's path); looked at {}",
            tried
                .iter()
                .take(6)
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )
    })
}
