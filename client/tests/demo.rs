//! The README's main job, `pntr demo`, end to end: it synthesizes the demo scene, builds a VLAD map,
//! localizes queries with the real models, and prints recall tables that must show real localization.

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
    // Two tables (with retrieval, then with the oracle): under each threshold header, 4 combined
    // recalls then 4 translation-only recalls.
    let lines: Vec<&str> = stdout.lines().collect();
    let tables: Vec<Vec<f64>> = lines
        .iter()
        .enumerate()
        .filter(|(_, l)| l.contains("(0.25m,2deg)"))
        .map(|(i, _)| {
            lines[i + 1]
                .split_whitespace()
                .map(|v| v.parse().unwrap())
                .collect()
        })
        .collect();
    assert_eq!(tables.len(), 2, "{stdout}");
    for r in &tables {
        assert_eq!(r.len(), 8, "{r:?}");
        assert!(r.iter().all(|x| (0.0..=1.0).contains(x)));
        assert!(r[0] >= r[1] && r[1] >= r[2] && r[2] >= r[3], "{r:?}");
    }
    assert!(
        tables[0][1] >= 0.5,
        "with retrieval, recall at (1m,10deg) {}",
        tables[0][1]
    );
    assert!(
        tables[1][1] >= 0.8,
        "with the oracle, recall at (1m,10deg) {}",
        tables[1][1]
    );
    assert!(
        stdout.contains("retrieval top-1 on the right Point"),
        "{stdout}"
    );
    assert!(stdout.contains("mean per query: extraction"), "{stdout}");
}
