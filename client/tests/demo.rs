//! The README's main job, `pntr demo`, end to end: it synthesizes the demo scene, reads it back and
//! localizes queries with the real models, printing a recall table that must show real localization.

use std::process::Command;

#[test]
fn demo_prints_a_recall_table_with_real_localization() {
    let dir = tempfile::tempdir().unwrap();
    let models = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../models");
    let out = Command::new(env!("CARGO_BIN_EXE_pntr"))
        .args([
            "demo",
            "--out",
            dir.path().to_str().unwrap(),
            "--queries",
            "20",
        ])
        .arg("--models")
        .arg(&models)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("synth000         23      138"), "{stdout}");
    assert!(stdout.contains("20 of 1089 queries"), "{stdout}");
    // The row under the threshold header: 4 combined recalls, then 4 translation-only recalls.
    let lines: Vec<&str> = stdout.lines().collect();
    let h = lines
        .iter()
        .position(|l| l.contains("(0.25m,2deg)"))
        .expect("recall header");
    let recalls: Vec<f64> = lines[h + 1]
        .split_whitespace()
        .map(|v| v.parse().unwrap())
        .collect();
    assert_eq!(recalls.len(), 8, "{}", lines[h + 1]);
    assert!(recalls.iter().all(|r| (0.0..=1.0).contains(r)));
    assert!(
        recalls[1] >= 0.8,
        "recall at (1m,10deg) {} on oracle retrieval",
        recalls[1]
    );
    assert!(
        recalls[0] >= recalls[1] && recalls[1] >= recalls[2] && recalls[2] >= recalls[3],
        "{recalls:?}"
    );
    assert!(stdout.contains("mean per query: extraction"), "{stdout}");
}
