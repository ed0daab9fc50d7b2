//! Mutation fuzzing of what crosses a trust boundary: encoded `LocalizeRequest`s (protobuf decoding,
//! then the server's validation and image/depth decoding) and map files (with section checksums
//! recomputed after mutating, so the mutations reach the record parser instead of stopping at the
//! checksum). Every input must give a value or an error, never a panic.
//!
//! CI runs a fixed-seed budget of iterations (a regression test); `PNTR_FUZZ_SECONDS=N` runs for N
//! seconds per target with a time-derived seed and prints the executions (`scripts/fuzz.sh`). Inputs
//! that ever panicked are kept in `tests/fuzz/` and replayed first.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use pntr_service::decode::{query, Limits};
use pntr_service::proto;
use pntr_service::wire;
use prost::Message;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn budget() -> (u64, Option<Duration>) {
    match std::env::var("PNTR_FUZZ_SECONDS")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
    {
        Some(s) => (
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_nanos() as u64,
            Some(Duration::from_secs_f64(s)),
        ),
        None => (20261122, None),
    }
}

/// One random edit: flip bits, overwrite, insert, delete, truncate, or splice a length-like value.
fn mutate(rng: &mut ChaCha8Rng, b: &mut Vec<u8>) {
    let n = b.len().max(1);
    match rng.gen_range(0..7) {
        0 => {
            for _ in 0..rng.gen_range(1..8) {
                let i = rng.gen_range(0..n);
                if let Some(x) = b.get_mut(i) {
                    *x ^= 1 << rng.gen_range(0..8);
                }
            }
        }
        1 => {
            let i = rng.gen_range(0..n);
            if let Some(x) = b.get_mut(i) {
                *x = [0, 0xff, 0x7f, 0x80, 1][rng.gen_range(0..5)];
            }
        }
        2 => {
            let i = rng.gen_range(0..=b.len());
            let k = rng.gen_range(1..16);
            b.splice(i..i, (0..k).map(|_| rng.gen::<u8>()));
        }
        3 => {
            let i = rng.gen_range(0..n);
            let k = rng.gen_range(1..64).min(b.len().saturating_sub(i));
            b.drain(i..i + k);
        }
        4 => b.truncate(rng.gen_range(0..n)),
        5 => {
            let i = rng.gen_range(0..n);
            let v: u64 = [0, 1, u32::MAX as u64, u64::MAX, 1 << 40][rng.gen_range(0..5)];
            for (k, byte) in v.to_le_bytes().iter().enumerate() {
                if let Some(x) = b.get_mut(i + k) {
                    *x = *byte;
                }
            }
        }
        _ => {
            let i = rng.gen_range(0..n);
            let j = rng.gen_range(0..n);
            if i < b.len() && j < b.len() {
                b.swap(i, j);
            }
        }
    }
}

fn corpus(target: &str) -> Vec<PathBuf> {
    let dir = pntr_tests::workspace_root().join("tests/fuzz").join(target);
    let mut v: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.path()).collect())
        .unwrap_or_default();
    v.retain(|p| {
        !p.file_name()
            .is_some_and(|n| n.to_string_lossy().starts_with('.'))
    });
    v.sort();
    v
}

/// Run `check` on the kept corpus, then on mutations of `seeds`; returns executions.
fn fuzz(target: &str, seeds: &[Vec<u8>], iterations: usize, check: &dyn Fn(&[u8])) -> usize {
    for p in corpus(target) {
        let b = std::fs::read(&p).unwrap();
        let r = catch_unwind(AssertUnwindSafe(|| check(&b)));
        assert!(r.is_ok(), "kept input {} panics again", p.display());
    }
    let (seed, time) = budget();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let t0 = Instant::now();
    let mut runs = 0;
    loop {
        match time {
            Some(t) if t0.elapsed() >= t => break,
            None if runs >= iterations => break,
            _ => {}
        }
        let mut b = seeds[runs % seeds.len()].clone();
        for _ in 0..rng.gen_range(1..4) {
            mutate(&mut rng, &mut b);
        }
        if catch_unwind(AssertUnwindSafe(|| check(&b))).is_err() {
            let dir = std::env::temp_dir().join(format!("pntr-fuzz-{target}"));
            std::fs::create_dir_all(&dir).unwrap();
            let p = dir.join(format!("crash-{seed}-{runs}"));
            std::fs::write(&p, &b).unwrap();
            panic!(
                "{target}: input {} panicked (kept at {})",
                runs,
                p.display()
            );
        }
        runs += 1;
    }
    eprintln!(
        "{target}: {runs} executions in {:.1} s, seed {seed}, no panic",
        t0.elapsed().as_secs_f64()
    );
    runs
}

fn small_view() -> (pntr_core::RgbImage, pntr_core::DepthMap) {
    let (w, h) = (24u32, 16u32);
    let rgb = pntr_core::RgbImage {
        width: w,
        height: h,
        data: (0..w * h * 3).map(|i| (i * 7) as u8).collect(),
    };
    let depth = pntr_core::DepthMap {
        width: w,
        height: h,
        data: (0..w * h).map(|i| 0.5 + (i % 13) as f32 * 0.1).collect(),
    };
    (rgb, depth)
}

#[test]
fn localize_requests_never_panic_the_decoder() {
    let (rgb, depth) = small_view();
    let k = pntr_core::Intrinsics {
        fx: 20.0,
        fy: 20.0,
        cx: 11.5,
        cy: 7.5,
        width: 24,
        height: 16,
        distortion: [0.0; 5],
    };
    let seeds: Vec<Vec<u8>> = vec![
        wire::raw_request(&rgb, &depth, Some(&k)).encode_to_vec(),
        wire::png_request(&rgb, &depth, Some(&k))
            .unwrap()
            .encode_to_vec(),
    ];
    let limits = Limits {
        max_width: 256,
        max_height: 256,
    };
    fuzz("request", &seeds, 20000, &|b| {
        if let Ok(req) = proto::LocalizeRequest::decode(b) {
            let _ = query(&req, &limits);
        }
    });
}

/// Recompute every section checksum of a (possibly mutated) map file whose section lengths still fit.
fn fix_checksums(b: &mut [u8]) {
    let mut pos = 12;
    while pos + 12 <= b.len() {
        let len = u64::from_le_bytes(b[pos + 4..pos + 12].try_into().unwrap()) as usize;
        let start = pos + 12;
        let Some(end) = start.checked_add(len).filter(|&e| e + 8 <= b.len()) else {
            return;
        };
        let sum = pntr_core::bytes::fnv1a(&b[start..end]);
        b[end..end + 8].copy_from_slice(&sum.to_le_bytes());
        pos = end + 8;
    }
}

fn small_map(dir: &Path) -> Vec<u8> {
    let index = pntr_tests::synthetic_dataset(dir, 2, 1, 4);
    let preset = pntr_pipeline::preset::Preset {
        keypoints: 32,
        vlad_words: 4,
        ..pntr_pipeline::preset::Preset::named("xfeat-mnn").unwrap()
    };
    let m = pntr_tests::build_map_with(&index, &preset, "f");
    let p = dir.join("m.pntrmap");
    pntr_pipeline::mapfile::save(&m, &p).unwrap();
    std::fs::read(&p).unwrap()
}

#[test]
fn map_files_never_panic_the_loader() {
    let dir = tempfile::tempdir().unwrap();
    let good = small_map(dir.path());
    let path = dir.path().join("mutated.pntrmap");
    let load = |b: &[u8]| {
        std::fs::write(&path, b).unwrap();
        let _ = pntr_pipeline::mapfile::load(&path, |_| {
            Err(pntr_retrieval::RetrievalError::Model(
                "no onnx model in this test".into(),
            ))
        });
    };
    // Half the mutations keep checksums valid, so they reach the record and section parsers.
    let mut fixed_seed = good.clone();
    fix_checksums(&mut fixed_seed);
    fuzz("mapfile", &[good.clone(), fixed_seed], 2000, &|b| {
        load(b);
        let mut c = b.to_vec();
        fix_checksums(&mut c);
        load(&c);
    });
}

/// A small Point file (2 database views with labels, 1 query, 8x6 pixels) so that mutations land in
/// HDF5 metadata (superblock, object headers, B-trees, heaps, filter messages) rather than pixels.
fn small_point(path: &Path, gzip: Option<u8>) -> Vec<u8> {
    let (w, h) = (8u32, 6u32);
    let view = |k: u32, labels: bool| pntr_dataset::View {
        world_from_camera: nalgebra::Isometry3::translation(k as f64, 0.0, 1.0),
        rgb: pntr_core::RgbImage::new(w, h, (0..w * h * 3).map(|i| (i * k) as u8).collect())
            .unwrap(),
        depth: pntr_core::DepthMap {
            width: w,
            height: h,
            data: (0..w * h).map(|i| 0.5 + (i % 5) as f32 * 0.3).collect(),
        },
        semantic: labels
            .then(|| pntr_core::LabelMap::new(w, h, (0..w * h).map(|i| i % 3).collect()).unwrap()),
        intrinsics: pntr_dataset::default_camera(w, h),
    };
    let record = pntr_dataset::PointRecord {
        db: vec![view(1, true), view(2, true)],
        queries: vec![view(3, false)],
        instance_categories: Some(vec![0, 4, 7]),
    };
    pntr_dataset::write_point(
        path,
        &record,
        &pntr_dataset::WriteOptions { gzip_level: gzip },
    )
    .unwrap();
    std::fs::read(path).unwrap()
}

/// What the reader child process made of one file.
#[derive(Debug, PartialEq)]
enum Verdict {
    /// Read completely.
    Read,
    /// Refused with an error.
    Refused,
    /// The HDF5 C library crashed, and the process said which file and field before dying.
    LibraryCrashNamed,
}

/// The reader child process (`pntr-h5-fuzz-target`): one path in, one verdict out. Restarted after a
/// crash.
struct H5Child {
    child: std::process::Child,
    stdin: std::process::ChildStdin,
    answers: std::sync::mpsc::Receiver<String>,
    stderr: PathBuf,
    dir: PathBuf,
    starts: usize,
}

impl H5Child {
    fn start(dir: &Path, starts: usize) -> Self {
        use std::io::BufRead;
        use std::process::{Command, Stdio};
        let stderr = dir.join(format!("child-{starts}.log"));
        let mut child = Command::new(env!("CARGO_BIN_EXE_pntr-h5-fuzz-target"))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&stderr).unwrap())
            .spawn()
            .expect("start pntr-h5-fuzz-target");
        let stdin = child.stdin.take().unwrap();
        let stdout = child.stdout.take().unwrap();
        let (tx, answers) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Self {
            child,
            stdin,
            answers,
            stderr,
            dir: dir.to_path_buf(),
            starts: starts + 1,
        }
    }

    /// Send one path. `Err` describes a failure the product must not have: a hang, a panic, or a
    /// crash that did not name the file.
    fn read(&mut self, path: &Path) -> Result<Verdict, String> {
        use std::io::Write;
        use std::sync::mpsc::RecvTimeoutError;
        let sent = writeln!(self.stdin, "{}", path.display()).and_then(|_| self.stdin.flush());
        let answer = match sent {
            Ok(()) => self.answers.recv_timeout(Duration::from_secs(30)),
            Err(_) => Err(RecvTimeoutError::Disconnected),
        };
        match answer.as_deref() {
            Ok("ok") => return Ok(Verdict::Read),
            Ok("err") => return Ok(Verdict::Refused),
            _ => {}
        }
        let _ = self.child.kill();
        let status = self.child.wait().ok();
        let log = std::fs::read_to_string(&self.stderr).unwrap_or_default();
        let named = log.contains("pntr: the HDF5 library crashed while reading `")
            && log.contains(&path.display().to_string());
        let signalled = {
            use std::os::unix::process::ExitStatusExt;
            status.is_some_and(|s| s.signal().is_some())
        };
        let verdict = if named && signalled && answer.is_err() {
            Ok(Verdict::LibraryCrashNamed)
        } else {
            let tail: Vec<&str> = log.lines().rev().take(8).collect();
            Err(format!(
                "answer {answer:?}, exit {status:?}, stderr tail:\n{}",
                tail.join("\n")
            ))
        };
        *self = H5Child::start(&self.dir.clone(), self.starts);
        verdict
    }
}

impl Drop for H5Child {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn hdf5_points_never_crash_the_reader_unexplained() {
    let dir = tempfile::tempdir().unwrap();
    let seeds = vec![
        small_point(&dir.path().join("gzip.hdf5"), Some(1)),
        small_point(&dir.path().join("plain.hdf5"), None),
    ];
    let child = std::cell::RefCell::new(H5Child::start(dir.path(), 0));
    // The unmutated seeds must read back: otherwise every mutation would be refused for one reason.
    for name in ["gzip.hdf5", "plain.hdf5"] {
        let verdict = child.borrow_mut().read(&dir.path().join(name));
        assert_eq!(verdict, Ok(Verdict::Read), "seed {name}");
    }
    // Kept inputs (each crashed libhdf5 1.10.8) must now be refused; one that crashes inside the
    // linked HDF5 where no check can reach (`hdf5-lib-*`) must at least name the file as it dies.
    for p in corpus("hdf5") {
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        let verdict = child.borrow_mut().read(&p);
        if name.starts_with("hdf5-lib-") {
            assert!(verdict.is_ok(), "{name}: {verdict:?}");
        } else {
            assert_eq!(verdict, Ok(Verdict::Refused), "{name}");
        }
    }
    let path = dir.path().join("mutated.hdf5");
    let verdicts = std::cell::RefCell::new([0usize; 3]);
    fuzz("hdf5", &seeds, 5000, &|b| {
        std::fs::write(&path, b).unwrap();
        let verdict = child.borrow_mut().read(&path);
        match verdict {
            Ok(v) => verdicts.borrow_mut()[v as usize] += 1,
            Err(e) => panic!("the HDF5 reader failed without naming the file: {e}"),
        }
    });
    let [read, refused, named] = *verdicts.borrow();
    eprintln!(
        "hdf5: {read} mutated files read, {refused} refused with an error, \
         {named} crashed inside libhdf5 naming the file"
    );
    // Both outcomes must occur, or the mutations are not reaching the reader.
    assert!(read > 0 && refused > 0, "read {read}, refused {refused}");
}
