//! The layers ARCHITECTURE.md draws, held by the source: the localization pipeline knows nothing of
//! making maps or of evaluation, no CLI subcommand module imports another, and the CLI's shared
//! modules import no subcommand and no one another in a circle.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(rust_files(&p));
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
    out
}

/// The `crate::NAME` modules a client source file refers to.
fn crate_refs(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    for (i, _) in text.match_indices("crate::") {
        let name: String = text[i + 7..]
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        if !name.is_empty() {
            out.insert(name);
        }
    }
    // `use crate::{a, b}` forms.
    for (i, _) in text.match_indices("use crate::{") {
        let end = text[i..].find('}').unwrap();
        for part in text[i + 12..i + end].split(',') {
            let name: String = part
                .trim()
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if !name.is_empty() {
                out.insert(name);
            }
        }
    }
    out
}

#[test]
fn the_pipeline_knows_nothing_of_mapping_or_evaluation() {
    let pipeline = root().join("server/pipeline");
    let manifest = std::fs::read_to_string(pipeline.join("Cargo.toml")).unwrap();
    for dep in ["pntr-mapping", "pntr-eval", "pntr-service"] {
        assert!(
            !manifest.contains(dep),
            "server/pipeline/Cargo.toml depends on {dep}"
        );
    }
    for f in rust_files(&pipeline.join("src")) {
        let text = std::fs::read_to_string(&f).unwrap();
        for word in ["pntr_mapping::", "pntr_eval::"] {
            // Doc comments may name where a thing moved; code may not use it.
            let used = text
                .lines()
                .any(|l| l.contains(word) && !l.trim_start().starts_with("//"));
            assert!(!used, "{} uses {word}", f.display());
        }
    }
    let mapping = std::fs::read_to_string(root().join("server/mapping/Cargo.toml")).unwrap();
    assert!(
        !mapping.contains("pntr-eval") && !mapping.contains("pntr-service"),
        "server/mapping depends on a layer above or beside it"
    );
}

#[test]
fn no_subcommand_imports_another_and_shared_modules_form_no_circle() {
    let src = root().join("client/src");
    let mut refs: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in rust_files(&src) {
        let name = f.file_stem().unwrap().to_string_lossy().to_string();
        if name == "main" {
            continue;
        }
        let text = std::fs::read_to_string(&f).unwrap();
        let mut r = crate_refs(&text);
        r.remove(&name);
        refs.insert(name, r);
    }
    assert!(refs.contains_key("build_cmd"), "client/src read");
    for (module, uses) in &refs {
        for u in uses {
            assert!(
                !u.ends_with("_cmd"),
                "client module `{module}` imports the subcommand module `{u}`: move what they share into a shared module"
            );
        }
    }
    // Shared modules (not `*_cmd`): no circle among them (depth-first search for a back edge).
    fn visit(
        m: &str,
        refs: &BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        path: &mut Vec<String>,
    ) {
        match state.get(m) {
            Some(2) => return,
            Some(1) => panic!("client modules import each other in a circle: {path:?} -> {m}"),
            _ => {}
        }
        state.insert(m.to_string(), 1);
        path.push(m.to_string());
        for u in refs.get(m).into_iter().flatten() {
            if refs.contains_key(u) {
                visit(u, refs, state, path);
            }
        }
        path.pop();
        state.insert(m.to_string(), 2);
    }
    let mut state = BTreeMap::new();
    for m in refs.keys() {
        visit(m, &refs, &mut state, &mut Vec::new());
    }
}
