//! The README's main job, `pntr demo`, end to end: it makes the demo scene and its map, starts a real
//! pntr-server on 127.0.0.1, localizes queries through it over gRPC with the real models, and prints a
//! recall table that must show real localization. A second run reuses the cached scene and map.

mod support;

use support::{ok, pntr, MODELS};

fn demo(dir: &std::path::Path, queries: &str) -> String {
    let out = dir.to_str().unwrap();
    ok(&pntr(&[
        "demo",
        "--out",
        out,
        "--queries",
        queries,
        "--models",
        MODELS,
    ]))
}

fn row(stdout: &str, name: &str) -> Vec<f64> {
    let line = stdout
        .lines()
        .find(|l| l.starts_with(name))
        .unwrap_or_else(|| panic!("no `{name}` row in\n{stdout}"));
    line[name.len()..]
        .split_whitespace()
        .map(|v| v.parse().unwrap())
        .collect()
}

#[test]
fn demo_serves_the_demo_map_and_prints_a_recall_table_with_real_localization() {
    let dir = tempfile::tempdir().unwrap();
    let stdout = demo(dir.path(), "20");
    assert!(
        stdout.contains("demo scene synth000: 23 Points, 138 database views, 1089 queries"),
        "{stdout}"
    );
    assert!(stdout.contains("pntr-server serving"), "{stdout}");
    assert!(stdout.contains("20 queries"), "{stdout}");
    for name in ["pipeline", "retrieval only"] {
        let r = row(&stdout, name);
        assert_eq!(r.len(), 8, "{r:?}");
        assert!(r.iter().all(|x| (0.0..=1.0).contains(x)));
        assert!(r[0] >= r[1] && r[1] >= r[2] && r[2] >= r[3], "{r:?}");
    }
    let p = row(&stdout, "pipeline");
    assert!(
        p[1] >= 0.7,
        "through the server, recall at (1m,10deg) {}",
        p[1]
    );
    assert!(stdout.contains("mean ms per query: extraction"), "{stdout}");
    // The scene and the map are cached: a second run reuses both.
    let map = dir.path().join("synth000-xfeat-mnn.pntrmap");
    let before = std::fs::metadata(&map).unwrap().modified().unwrap();
    let again = demo(dir.path(), "2");
    assert!(again.contains("2 queries"), "{again}");
    assert_eq!(std::fs::metadata(&map).unwrap().modified().unwrap(), before);
    // The demo map carries its own calibration, fitted on the scene's queries.
    let own = support::map_info(&map, &[]);
    assert_eq!(
        (&own["calibration"]["source"], &own["calibration"]["stale"]),
        (&"map".into(), &false.into()),
        "{own}"
    );
    // A cached map without one (an older pntr's) is rebuilt with it.
    let root = dir.path().to_str().unwrap();
    support::build_db(
        &map,
        &[
            "--dataset",
            root,
            "--scene",
            "synth000",
            "--no-self-calibration",
        ],
    );
    assert_eq!(
        support::map_info(&map, &[])["calibration"]["source"],
        "shipped"
    );
    let rebuilt = demo(dir.path(), "2");
    assert!(rebuilt.contains("2 queries"), "{rebuilt}");
    let own_again = support::map_info(&map, &[]);
    assert_eq!(own_again["calibration"]["source"], "map", "{own_again}");
    assert_eq!(
        own_again["calibration"]["threshold"], own["calibration"]["threshold"],
        "the same scene fits the same calibration"
    );
}
