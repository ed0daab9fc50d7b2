//! Helpers shared by the end-to-end tests in this folder.
//!
//! These tests cross process and language boundaries (h5py, the CLI, later the gRPC server), so they
//! live in their own crate at the top of the workspace, above every library they exercise.

use std::path::PathBuf;
use std::process::Command;

/// The Python interpreter with h5py and numpy: `$PNTR_PYTHON`, else the venv `scripts/setup.sh` makes.
///
/// Panics with the fix when it is missing: these tests check compatibility with the reference
/// tooling and must not pass silently without it.
pub fn python() -> PathBuf {
    let p = std::env::var_os("PNTR_PYTHON")
        .map(PathBuf::from)
        .map(|p| {
            if p.is_relative() {
                workspace_root().join(p)
            } else {
                p
            }
        })
        .unwrap_or_else(|| workspace_root().join(".deps/venv/bin/python"));
    let ok = Command::new(&p)
        .args(["-c", "import h5py, numpy"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        ok,
        "{} cannot import h5py and numpy: run `bash scripts/setup.sh` (or set PNTR_PYTHON)",
        p.display()
    );
    p
}

/// The workspace root (the folder holding the top-level Cargo.toml).
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_path_buf()
}

/// Run a Python script from `tests/python/` and return its stdout; panics with stderr on failure.
pub fn run_python(script: &str, args: &[&std::ffi::OsStr]) -> String {
    let out = Command::new(python())
        .arg(workspace_root().join("tests/python").join(script))
        .args(args)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "{script} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 output")
}

/// The committed ONNX models.
pub fn models() -> PathBuf {
    workspace_root().join("models")
}

/// Generate one synthetic scene (`synth000`) of `points` Points with `queries` query draws each into
/// `root`, and list it.
pub fn synthetic_dataset(
    root: &std::path::Path,
    points: usize,
    queries: usize,
    seed: u64,
) -> pntr_dataset::DatasetIndex {
    let cfg = pntr_synth::SynthConfig {
        points_per_scene: points,
        queries_per_point: queries,
        seed,
        ..Default::default()
    };
    pntr_synth::synthesize(&cfg, root, pntr_synth::plan_all(&cfg), &|| {}).expect("synthesize");
    pntr_dataset::DatasetIndex::open(root).expect("list the generated dataset")
}

/// Build the map `map_id` of every scene of `index` with the named preset and the committed models.
pub fn build_map(
    index: &pntr_dataset::DatasetIndex,
    preset: &str,
    map_id: &str,
) -> pntr_pipeline::map::Map {
    let preset = pntr_pipeline::preset::Preset::named(preset).expect("preset");
    let stage = preset
        .map_feature_config(models())
        .build()
        .expect("models load");
    let scenes: Vec<_> = index.scenes.iter().collect();
    pntr_pipeline::map::build(map_id, &scenes, &preset, &stage, &models(), &mut |_, _| {})
        .expect("map builds")
}
