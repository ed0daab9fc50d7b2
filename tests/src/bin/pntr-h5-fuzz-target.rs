//! Child process of the HDF5 fuzz target in `tests/fuzz_inputs.rs`.
//!
//! The HPointLoc reader sits on the HDF5 C library, which may abort or crash on a damaged file instead
//! of returning an error, and a crash in-process would take the whole test harness down with it. So
//! the harness runs the reader here: it reads one file path per line from stdin, opens the file with
//! [`pntr_dataset::PointReader`], reads every view, and answers `ok` or `err` on stdout. The harness
//! treats a missing answer (a signal, an abort, a panic, a hang) as a finding for the input it sent.

use std::io::{BufRead, Write};
use std::path::Path;

fn main() {
    let stdin = std::io::stdin();
    let mut out = std::io::stdout().lock();
    for line in stdin.lock().lines() {
        let Ok(line) = line else { break };
        let verdict = match pntr_dataset::PointReader::open(Path::new(&line)).and_then(|r| {
            r.read_all()?;
            Ok(())
        }) {
            Ok(()) => "ok",
            Err(_) => "err",
        };
        if writeln!(out, "{verdict}")
            .and_then(|_| out.flush())
            .is_err()
        {
            break;
        }
    }
}
