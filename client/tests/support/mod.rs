//! Checks shared by the CLI tests.

// Each test binary uses its own part of this module.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

/// Run the `pntr` binary under test (without a token from the environment).
pub fn pntr(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pntr"))
        .args(args)
        .env_remove("PNTR_TOKEN")
        .output()
        .expect("pntr runs")
}

/// Its stdout, asserting it succeeded (stdout and stderr shown when not).
pub fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The Python interpreter with the test packages: `$PNTR_PYTHON`, else set-up's venv.
pub fn python() -> std::path::PathBuf {
    std::env::var_os("PNTR_PYTHON")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../.deps/venv/bin/python"))
}

/// An MCAP file read back with the format's own Python reader (`mcap`, not pntr's code): for each
/// topic its schema name and encoding, message encoding and message count, and every JSON message
/// of `json_topic` decoded.
pub fn read_mcap(path: &Path, json_topic: &str) -> serde_json::Value {
    const SCRIPT: &str = r#"
import json, sys
from mcap.reader import make_reader
topics, decoded = {}, []
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f)
    summary = reader.get_summary()
    for schema, channel, message in reader.iter_messages():
        t = topics.setdefault(channel.topic, {"schema": schema.name if schema else "",
                                              "schema_encoding": schema.encoding if schema else "",
                                              "message_encoding": channel.message_encoding, "count": 0})
        t["count"] += 1
        if channel.topic == sys.argv[2]:
            decoded.append(json.loads(message.data))
print(json.dumps({"topics": topics, "json": decoded,
                  "statistics_messages": summary.statistics.message_count if summary and summary.statistics else None}))
"#;
    let out = Command::new(python())
        .args(["-c", SCRIPT])
        .arg(path)
        .arg(json_topic)
        .output()
        .expect("python runs (bash scripts/setup.sh makes .deps/venv, or set PNTR_PYTHON)");
    assert!(
        out.status.success(),
        "the mcap reader failed on {}:\n{}",
        path.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("JSON from the reader")
}

/// Its stderr, asserting it failed.
pub fn err(out: &Output) -> String {
    assert!(!out.status.success(), "expected a failure");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A picture `pntr ... --plot` wrote: `dir/name.png` decodes at `size` with more than a few colours
/// (lines and text, not a blank canvas), and `dir/name.svg` is an SVG document holding every one of
/// `texts` (titles, axis names, legend entries).
pub fn assert_picture(dir: &Path, name: &str, size: (u32, u32), texts: &[&str]) {
    let png = dir.join(format!("{name}.png"));
    let img = image::open(&png)
        .unwrap_or_else(|e| panic!("{}: {e}", png.display()))
        .to_rgb8();
    assert_eq!(img.dimensions(), size, "{}", png.display());
    let colours: std::collections::BTreeSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    assert!(
        colours.len() > 20,
        "{}: only {} colours",
        png.display(),
        colours.len()
    );
    let svg_path = dir.join(format!("{name}.svg"));
    let svg = std::fs::read_to_string(&svg_path).unwrap();
    assert!(
        svg.trim_start().starts_with("<svg") && svg.trim_end().ends_with("</svg>"),
        "{}",
        svg_path.display()
    );
    for t in texts {
        assert!(svg.contains(t), "{} lacks \"{t}\"", svg_path.display());
    }
    // Nothing half-written is left beside them.
    for e in std::fs::read_dir(dir).unwrap() {
        let n = e.unwrap().file_name();
        assert!(!n.to_string_lossy().contains(".partial"), "{n:?}");
    }
}
