//! The documentation as a user meets it: every relative link in README.md, BENCHMARKS.md,
//! deploy/README.md and docs/**/*.md resolves (files, folders, and `#anchors` into Markdown files by
//! GitHub's heading slugs), every fenced block marked `checked` runs, and every Python block
//! compiles. The convention for checked blocks is described in docs/README.md, "How the examples are
//! checked": per Markdown file a fresh temporary folder, its `sh checked` blocks run there in order
//! with `bash -e -u -o pipefail`, `pntr` and `pntr-server` (the binaries under test) first on PATH,
//! `python` the set-up venv's with `pntr_client` built from client/python, a time limit per block
//! (`timeout=SECONDS`, default 60), and `file=NAME` blocks written to NAME instead of run.

use std::collections::{BTreeMap, BTreeSet};
use std::ffi::OsString;
use std::fs;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// Time a checked block may run unless its info string says `timeout=SECONDS`.
const DEFAULT_TIMEOUT_S: u64 = 60;
/// Lines of a failed block's output shown in the failure.
const TAIL_LINES: usize = 40;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("client/ has a parent")
        .to_path_buf()
}

/// The Markdown files under test, relative to the repository root, in a stable order.
fn markdown_files() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<PathBuf> = fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.expect("a directory entry").path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p);
            }
        }
    }
    let root = repo();
    let mut files: Vec<PathBuf> = ["README.md", "BENCHMARKS.md", "deploy/README.md"]
        .iter()
        .map(|f| root.join(f))
        .collect();
    walk(&root.join("docs"), &mut files);
    for f in &files {
        assert!(f.is_file(), "{} is missing", f.display());
    }
    files
}

fn shown(path: &Path) -> String {
    path.strip_prefix(repo())
        .unwrap_or(path)
        .display()
        .to_string()
}

/// A fenced code block: the line of its opening fence (1-based), its info string and its text.
struct Block {
    line: usize,
    info: String,
    text: String,
}

impl Block {
    fn words(&self) -> impl Iterator<Item = &str> {
        self.info.split_whitespace()
    }

    fn language(&self) -> &str {
        self.words().next().unwrap_or("")
    }

    fn checked(&self) -> bool {
        self.words().any(|w| w == "checked")
    }

    fn attribute(&self, key: &str) -> Option<&str> {
        self.words()
            .find_map(|w| w.strip_prefix(key).and_then(|v| v.strip_prefix('=')))
    }
}

/// The opening of a fence: its indentation, character, length and info string.
fn fence_open(line: &str) -> Option<(usize, char, usize, &str)> {
    let trimmed = line.trim_start();
    let indent = line.len() - trimmed.len();
    let c = trimmed.chars().next()?;
    if c != '`' && c != '~' {
        return None;
    }
    let n = trimmed.chars().take_while(|&x| x == c).count();
    if n < 3 {
        return None;
    }
    let info = trimmed[n..].trim();
    // A backtick fence's info string may not hold backticks (that line is inline code).
    if c == '`' && info.contains('`') {
        return None;
    }
    Some((indent, c, n, info))
}

fn fence_closes(line: &str, c: char, n: usize) -> bool {
    let t = line.trim();
    t.len() >= n && t.chars().all(|x| x == c)
}

/// Split a Markdown file into its fenced blocks and the lines outside them (1-based numbers).
fn parse(text: &str) -> (Vec<Block>, Vec<(usize, String)>) {
    let lines: Vec<&str> = text.lines().collect();
    let mut blocks = Vec::new();
    let mut prose = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let Some((indent, c, n, info)) = fence_open(lines[i]) else {
            prose.push((i + 1, lines[i].to_string()));
            i += 1;
            continue;
        };
        let start = i + 1;
        let mut body = String::new();
        i += 1;
        while i < lines.len() && !fence_closes(lines[i], c, n) {
            let l = lines[i];
            let strip = l.len() - l.trim_start().len();
            body.push_str(&l[strip.min(indent)..]);
            body.push('\n');
            i += 1;
        }
        i += 1;
        blocks.push(Block {
            line: start,
            info: info.to_string(),
            text: body,
        });
    }
    (blocks, prose)
}

/// A line with its inline code spans blanked out, so that link-like text inside them is ignored.
fn without_code_spans(line: &str) -> String {
    let chars: Vec<char> = line.chars().collect();
    let mut out = String::new();
    let mut i = 0;
    while i < chars.len() {
        if chars[i] != '`' {
            out.push(chars[i]);
            i += 1;
            continue;
        }
        let run = chars[i..].iter().take_while(|&&c| c == '`').count();
        // Find the closing run of the same length.
        let mut j = i + run;
        let mut close = None;
        while j < chars.len() {
            if chars[j] == '`' {
                let r = chars[j..].iter().take_while(|&&c| c == '`').count();
                if r == run {
                    close = Some(j);
                    break;
                }
                j += r;
            } else {
                j += 1;
            }
        }
        match close {
            Some(j) => {
                out.extend(std::iter::repeat_n(' ', j + run - i));
                i = j + run;
            }
            None => {
                out.extend(&chars[i..i + run]);
                i += run;
            }
        }
    }
    out
}

/// Link destinations on a line: inline links and images `[..](dest)` and reference definitions
/// `[label]: dest`.
fn link_targets(line: &str) -> Vec<String> {
    let line = without_code_spans(line);
    let mut out = Vec::new();
    let trimmed = line.trim_start();
    if trimmed.starts_with('[') {
        if let Some(k) = trimmed.find("]:") {
            if let Some(dest) = trimmed[k + 2..].split_whitespace().next() {
                out.push(dest.trim_matches(['<', '>']).to_string());
            }
        }
    }
    let mut rest = line.as_str();
    while let Some(k) = rest.find("](") {
        let after = &rest[k + 2..];
        let dest = if let Some(inner) = after.strip_prefix('<') {
            inner.split('>').next().unwrap_or("").to_string()
        } else {
            let mut depth = 0usize;
            let mut end = after.len();
            for (idx, ch) in after.char_indices() {
                match ch {
                    '(' => depth += 1,
                    ')' if depth == 0 => {
                        end = idx;
                        break;
                    }
                    ')' => depth -= 1,
                    c if c.is_whitespace() => {
                        end = idx;
                        break;
                    }
                    _ => {}
                }
            }
            after[..end].to_string()
        };
        out.push(dest);
        rest = after;
    }
    out
}

/// The text GitHub renders for a heading's source, for its slug: links and images become their
/// text, inline code keeps its content, HTML tags go.
fn heading_text(source: &str) -> String {
    let mut s = String::new();
    let chars: Vec<char> = source.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        match chars[i] {
            '!' if chars.get(i + 1) == Some(&'[') => i += 1,
            '[' => i += 1,
            ']' if chars.get(i + 1) == Some(&'(') => {
                // Skip the destination.
                let mut depth = 0;
                i += 2;
                while i < chars.len() {
                    match chars[i] {
                        '(' => depth += 1,
                        ')' if depth == 0 => break,
                        ')' => depth -= 1,
                        _ => {}
                    }
                    i += 1;
                }
                i += 1;
            }
            '<' => {
                while i < chars.len() && chars[i] != '>' {
                    i += 1;
                }
                i += 1;
            }
            '`' => i += 1,
            c => {
                s.push(c);
                i += 1;
            }
        }
    }
    s
}

/// GitHub's slug of a heading: lower case, everything but letters, digits, `_`, `-` and spaces
/// dropped, spaces turned into hyphens.
fn slug(text: &str) -> String {
    let mut out = String::new();
    for c in heading_text(text).trim().chars() {
        if c == ' ' {
            out.push('-');
        } else if c.is_alphanumeric() || c == '_' || c == '-' {
            out.extend(c.to_lowercase());
        }
    }
    out
}

/// Every anchor of a Markdown file: heading slugs (repeats get `-1`, `-2`, ...) and HTML
/// `id="..."` / `name="..."` attributes.
fn anchors(text: &str) -> BTreeSet<String> {
    let (_, prose) = parse(text);
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let mut out = BTreeSet::new();
    for (_, line) in &prose {
        let t = line.trim_start();
        let hashes = t.chars().take_while(|&c| c == '#').count();
        if (1..=6).contains(&hashes) && t[hashes..].starts_with(' ') {
            let title = t[hashes..].trim().trim_end_matches('#').trim();
            let base = slug(title);
            let n = seen.entry(base.clone()).or_insert(0);
            out.insert(if *n == 0 {
                base.clone()
            } else {
                format!("{base}-{n}")
            });
            *n += 1;
        }
        for key in ["id=\"", "name=\""] {
            let mut rest = line.as_str();
            while let Some(k) = rest.find(key) {
                let after = &rest[k + key.len()..];
                if let Some(end) = after.find('"') {
                    out.insert(after[..end].to_string());
                }
                rest = after;
            }
        }
    }
    out
}

fn percent_decoded(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' && i + 2 < bytes.len() {
            let hex = std::str::from_utf8(&bytes[i + 1..i + 3]).ok();
            if let Some(b) = hex.and_then(|h| u8::from_str_radix(h, 16).ok()) {
                out.push(b);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[test]
fn every_relative_link_and_anchor_resolves() {
    let mut problems = Vec::new();
    let mut cache: BTreeMap<PathBuf, BTreeSet<String>> = BTreeMap::new();
    let mut anchors_of = |p: &Path| -> BTreeSet<String> {
        cache
            .entry(p.to_path_buf())
            .or_insert_with(|| anchors(&fs::read_to_string(p).unwrap_or_default()))
            .clone()
    };
    let mut checked = 0;
    for file in markdown_files() {
        let text = fs::read_to_string(&file).expect("readable Markdown");
        let (_, prose) = parse(&text);
        let dir = file.parent().expect("a file has a folder");
        for (line, content) in &prose {
            for dest in link_targets(content) {
                if dest.is_empty()
                    || dest.contains("://")
                    || dest.starts_with("mailto:")
                    || dest.starts_with("tel:")
                {
                    continue;
                }
                checked += 1;
                let (path, anchor) = match dest.split_once('#') {
                    Some((p, a)) => (p, Some(a)),
                    None => (dest.as_str(), None),
                };
                let target = if path.is_empty() {
                    file.clone()
                } else {
                    dir.join(percent_decoded(path))
                };
                let at = format!("{}:{line}: link `{dest}`", shown(&file));
                if !target.exists() {
                    problems.push(format!("{at}: {} does not exist", shown(&target)));
                    continue;
                }
                if let Some(a) = anchor.filter(|a| !a.is_empty()) {
                    if target.extension().is_some_and(|x| x == "md") {
                        let known = anchors_of(&target);
                        if !known.contains(a) {
                            problems.push(format!(
                                "{at}: no heading with the anchor #{a} in {}",
                                shown(&target)
                            ));
                        }
                    }
                }
            }
        }
    }
    assert!(
        checked > 50,
        "only {checked} links found: is the parser broken?"
    );
    assert!(
        problems.is_empty(),
        "{} broken link(s):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn slugs_follow_github() {
    assert_eq!(
        slug("End to end: `make demo` (the README's main job)"),
        "end-to-end-make-demo-the-readmes-main-job"
    );
    assert_eq!(
        slug("ROS 2: from an answer to `map -> odom`"),
        "ros-2-from-an-answer-to-map---odom"
    );
    assert_eq!(
        slug("4. Add a later session: extend"),
        "4-add-a-later-session-extend"
    );
    assert_eq!(
        slug("Recall at (0.25 m, 2°) with [a link](x.md)"),
        "recall-at-025-m-2-with-a-link"
    );
    let a = anchors("# A\n\n```\n# not a heading\n```\n## A\n### B_c\n");
    assert_eq!(
        a,
        ["a", "a-1", "b_c"].iter().map(|s| s.to_string()).collect()
    );
    assert_eq!(
        link_targets("see [x](a.md#b) and `[no](c.md)` or ![i](img.png \"t\")"),
        vec!["a.md#b".to_string(), "img.png".to_string()]
    );
}

/// A folder for files that must not land in a block's working folder.
fn scratch(prefix: &str) -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix(prefix)
        .tempdir()
        .expect("a temporary folder")
}

/// The Python the set-up installed (`PNTR_PYTHON`, else `.deps/venv/bin/python`).
fn python() -> Option<PathBuf> {
    std::env::var_os("PNTR_PYTHON")
        .map(PathBuf::from)
        .filter(|p| p.is_file())
        .or_else(|| Some(repo().join(".deps/venv/bin/python")).filter(|p| p.is_file()))
}

/// Kill a block's whole process group (it was started as its own group's leader).
fn kill_group(pid: u32) {
    let _ = Command::new("kill")
        .args(["-KILL", "--", &format!("-{pid}")])
        .stderr(Stdio::null())
        .status();
}

fn tail(text: &str) -> String {
    let lines: Vec<&str> = text.lines().collect();
    let from = lines.len().saturating_sub(TAIL_LINES);
    lines[from..].join("\n")
}

/// The environment of checked blocks (see docs/README.md): the caller's without its `PNTR_*`
/// variables, then the binaries under test and a `python` first on PATH, the libraries set-up
/// installed, `PNTR_REPO`, `PNTR_PYTHON` and the client package on PYTHONPATH.
fn block_env(bin: &Path, shim: &Path, pylib: Option<&Path>) -> Vec<(OsString, OsString)> {
    let root = repo();
    let mut env: Vec<(OsString, OsString)> = std::env::vars_os()
        .filter(|(k, _)| !k.to_string_lossy().starts_with("PNTR_"))
        .filter(|(k, _)| k != "PATH" && k != "PYTHONPATH")
        .collect();
    let mut path = OsString::from(bin);
    path.push(":");
    path.push(shim);
    if let Some(old) = std::env::var_os("PATH") {
        path.push(":");
        path.push(old);
    }
    env.push(("PATH".into(), path));
    env.push(("PNTR_REPO".into(), root.clone().into()));
    if let Some(py) = python() {
        env.push(("PNTR_PYTHON".into(), py.into()));
    }
    if let Some(lib) = pylib {
        env.push(("PYTHONPATH".into(), lib.into()));
    }
    for (var, lib) in [
        (
            "ORT_DYLIB_PATH",
            ".deps/onnxruntime/libonnxruntime.so.1.31.1",
        ),
        (
            "OPENVINO_DYLIB_PATH",
            ".deps/openvino/libopenvino_c.so.2641",
        ),
    ] {
        if std::env::var_os(var).is_none() && root.join(lib).is_file() {
            env.push((var.into(), root.join(lib).into()));
        }
    }
    env
}

/// Build the Python client package offline into `dir` (what `pip install client/python` installs),
/// with the set-up venv's setuptools (the gRPC stubs are committed).
fn install_python_client(py: &Path, dir: &Path) {
    let out = Command::new(py)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--no-build-isolation",
            "--no-deps",
            "--no-index",
            "--target",
        ])
        .arg(dir)
        .arg(repo().join("client/python"))
        .output()
        .expect("pip runs");
    assert!(
        out.status.success(),
        "building client/python with {} failed (run scripts/setup.sh):\n{}{}",
        py.display(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn checked_blocks_run() {
    let pntr = PathBuf::from(env!("CARGO_BIN_EXE_pntr"));
    let bin = pntr.parent().expect("pntr has a folder").to_path_buf();
    let server = bin.join("pntr-server");
    assert!(
        server.is_file(),
        "pntr-server is not built beside pntr in {}: the docs' examples need both. Build it with \
         `cargo build -p pntr-service` (a workspace build, such as `make test`, builds it), then run \
         this test again",
        bin.display()
    );
    let files: Vec<(PathBuf, Vec<Block>)> = markdown_files()
        .into_iter()
        .map(|f| {
            let text = fs::read_to_string(&f).expect("readable Markdown");
            let blocks = parse(&text).0.into_iter().filter(Block::checked).collect();
            (f, blocks)
        })
        .filter(|(_, b): &(PathBuf, Vec<Block>)| !b.is_empty())
        .collect();
    assert!(!files.is_empty(), "no checked blocks found");

    let tools = scratch("pntr-docs-tools-");
    let shim = tools.path().join("bin");
    fs::create_dir_all(&shim).expect("a folder");
    let needs_python = files
        .iter()
        .flat_map(|(_, b)| b)
        .any(|b| b.text.contains("python") || b.language() == "python");
    let pylib = if needs_python {
        let py = python().unwrap_or_else(|| {
            panic!(
                "checked blocks use Python, but neither PNTR_PYTHON nor {} is a file: run scripts/setup.sh",
                repo().join(".deps/venv/bin/python").display()
            )
        });
        // A wrapper, not a symlink: a venv's Python finds its packages from the path it is run by.
        for name in ["python", "python3"] {
            let wrapper = shim.join(name);
            fs::write(
                &wrapper,
                format!("#!/bin/sh\nexec '{}' \"$@\"\n", py.display()),
            )
            .expect("a Python wrapper");
            fs::set_permissions(
                &wrapper,
                std::os::unix::fs::PermissionsExt::from_mode(0o755),
            )
            .expect("an executable wrapper");
        }
        let lib = tools.path().join("pylib");
        install_python_client(&py, &lib);
        Some(lib)
    } else {
        None
    };
    let env = block_env(&bin, &shim, pylib.as_deref());

    let mut failures = Vec::new();
    let mut ran = 0;
    let started = Instant::now();
    for (file, blocks) in &files {
        let name = shown(file);
        let work = scratch("pntr-docs-");
        for b in blocks {
            if let Some(f) = b.attribute("file") {
                fs::write(work.path().join(f), &b.text).expect("a block's file");
            }
        }
        let mut failed_here = false;
        for b in blocks.iter().filter(|b| b.attribute("file").is_none()) {
            let at = format!("{name}:{}", b.line);
            if !matches!(b.language(), "sh" | "bash") {
                failures.push(format!(
                    "{at}: a checked block must be `sh` (or carry file=NAME), not `{}`",
                    b.language()
                ));
                continue;
            }
            let timeout = b
                .attribute("timeout")
                .map(|t| t.parse().unwrap_or_else(|_| panic!("{at}: timeout={t}")))
                .unwrap_or(DEFAULT_TIMEOUT_S);
            let script = tools.path().join("block.sh");
            fs::write(&script, &b.text).expect("the block's script");
            let log_path = tools.path().join("block.log");
            let log = fs::File::create(&log_path).expect("a log file");
            let t0 = Instant::now();
            let mut child = Command::new("bash")
                .args(["-e", "-u", "-o", "pipefail"])
                .arg(&script)
                .current_dir(work.path())
                .env_clear()
                .envs(env.iter().map(|(k, v)| (k, v)))
                .stdin(Stdio::null())
                .stdout(log.try_clone().expect("a log handle"))
                .stderr(log)
                .process_group(0)
                .spawn()
                .expect("bash runs");
            let status = loop {
                if let Some(s) = child.try_wait().expect("waiting for a block") {
                    break Some(s);
                }
                if t0.elapsed() > Duration::from_secs(timeout) {
                    break None;
                }
                std::thread::sleep(Duration::from_millis(50));
            };
            kill_group(child.id());
            let _ = child.wait();
            ran += 1;
            let output = fs::read_to_string(&log_path).unwrap_or_default();
            eprintln!("{at}: {:.1} s", t0.elapsed().as_secs_f64());
            let why = match status {
                Some(s) if s.success() => continue,
                Some(s) => format!("exited with {s}"),
                None => format!("ran past its {timeout} s limit"),
            };
            let earlier = if failed_here {
                " (after an earlier block of this file failed)"
            } else {
                ""
            };
            failures.push(format!(
                "{at}: the checked block {why}{earlier}; lines of `bash: line N` are the block's \
                 line N. Its output ends:\n{}\n",
                tail(&output)
            ));
            failed_here = true;
        }
        if failed_here {
            // Keep the folder to look at what the blocks left.
            let kept = work.keep();
            failures.push(format!("  ({name}'s folder kept: {})", kept.display()));
        }
    }
    eprintln!(
        "{ran} checked blocks in {} files, {:.1} s",
        files.len(),
        started.elapsed().as_secs_f64()
    );
    assert!(
        failures.is_empty(),
        "checked blocks failed:\n{}",
        failures.join("\n")
    );
}

#[test]
fn python_blocks_compile() {
    let Some(py) = python() else {
        panic!("no Python to compile the docs' Python blocks with: run scripts/setup.sh");
    };
    let dir = scratch("pntr-docs-py-");
    let mut paths = Vec::new();
    for file in markdown_files() {
        let text = fs::read_to_string(&file).expect("readable Markdown");
        for b in parse(&text).0 {
            if b.language() == "python" {
                let p = dir.path().join(format!(
                    "{}-line-{}.py",
                    shown(&file).replace('/', "_"),
                    b.line
                ));
                fs::write(&p, &b.text).expect("a block's file");
                paths.push(p);
            }
        }
    }
    assert!(!paths.is_empty(), "no Python blocks found");
    let out = Command::new(&py)
        .args([
            "-c",
            "import sys\nfor p in sys.argv[1:]:\n    compile(open(p).read(), p, 'exec')",
        ])
        .args(&paths)
        .output()
        .expect("Python runs");
    assert!(
        out.status.success(),
        "a Python block does not compile (the file name is FILE-line-N.py):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
