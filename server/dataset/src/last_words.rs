//! Naming the file when the HDF5 C library crashes.
//!
//! The HDF5 C library can crash on damaged files instead of returning an error: fuzzing found three
//! such inputs for Debian's libhdf5 1.10.8 (see RELIABILITY.md). The statically linked HDF5 2.2 and the
//! reader's structural checks refuse all of them, but a crash inside C code cannot be caught and turned
//! into an error. What can be done is to make the death say why: every call into HDF5 goes through
//! [`h5`], which records "reading field F of file P" in a fixed static buffer while the call runs,
//! and a handler for SIGSEGV, SIGBUS, SIGILL, SIGFPE and SIGABRT writes that note to stderr (with
//! `write(2)`, which is async-signal-safe) and then hands the signal to the handler that was there
//! before (Rust's stack-overflow reporter or the default), so the process still dies with the signal
//! and exit status it would have had.
//!
//! The calls hold one process-wide lock while the note is set, so the note always belongs to the call
//! that is running. hdf5-metno serialises every HDF5 call behind its own global lock already, so this
//! costs no parallelism.
#![allow(unsafe_code)] // sigaction and write(2) are FFI; each use is commented.

use std::path::Path;
use std::sync::atomic::{AtomicU8, AtomicUsize, Ordering};
use std::sync::{Mutex, Once, OnceLock};

const CAP: usize = 1536;
const SIGNALS: [libc::c_int; 5] = [
    libc::SIGSEGV,
    libc::SIGBUS,
    libc::SIGILL,
    libc::SIGFPE,
    libc::SIGABRT,
];

static NOTE: [AtomicU8; CAP] = [const { AtomicU8::new(0) }; CAP];
static NOTE_LEN: AtomicUsize = AtomicUsize::new(0);
static CALLS: Mutex<()> = Mutex::new(());
static INSTALL: Once = Once::new();
static PREVIOUS: OnceLock<Vec<(libc::c_int, libc::sigaction)>> = OnceLock::new();

/// Run `f`, one call into HDF5 on behalf of `field` of `path`, with the crash note set.
///
/// `f` must not call `h5` itself (the lock is not re-entrant).
pub(crate) fn h5<T>(path: &Path, field: &str, f: impl FnOnce() -> T) -> T {
    INSTALL.call_once(install);
    let _held = CALLS.lock().unwrap_or_else(|e| e.into_inner());
    let note = format!(
        "\npntr: the HDF5 library crashed while reading `{field}` of {}: the file is damaged \
         (the HDF5 library does not check every structure it reads). Replace or remove this file.\n",
        path.display()
    );
    let bytes = note.as_bytes();
    let n = bytes.len().min(CAP);
    NOTE_LEN.store(0, Ordering::Release);
    for (slot, b) in NOTE.iter().zip(&bytes[..n]) {
        slot.store(*b, Ordering::Relaxed);
    }
    NOTE_LEN.store(n, Ordering::Release);
    let out = f();
    NOTE_LEN.store(0, Ordering::Release);
    out
}

extern "C" fn on_fatal(sig: libc::c_int, _info: *mut libc::siginfo_t, _ctx: *mut libc::c_void) {
    let n = NOTE_LEN.swap(0, Ordering::AcqRel).min(CAP);
    if n > 0 {
        let mut buf = [0u8; CAP];
        for (b, slot) in buf.iter_mut().zip(NOTE.iter()).take(n) {
            *b = slot.load(Ordering::Relaxed);
        }
        // SAFETY: write(2) is async-signal-safe; the buffer is a live stack array of at least n bytes.
        unsafe {
            libc::write(2, buf.as_ptr().cast(), n);
        }
    }
    match PREVIOUS
        .get()
        .and_then(|p| p.iter().find(|(s, _)| *s == sig))
    {
        // SAFETY: restores a disposition sigaction handed back to us at install time. Returning
        // from this handler re-runs the faulting instruction (or, for abort(), re-raises), which
        // then meets the previous handler, so the process ends exactly as it would have.
        Some((_, prev)) => unsafe {
            libc::sigaction(sig, prev, std::ptr::null_mut());
        },
        // SAFETY: as above, with the default disposition (install had not finished recording).
        None => unsafe {
            libc::signal(sig, libc::SIG_DFL);
        },
    }
}

fn install() {
    let mut previous = Vec::new();
    for sig in SIGNALS {
        // SAFETY: a zeroed sigaction is a valid "no handler, empty mask" value to fill in; the
        // handler only touches atomics, a stack buffer, write(2) and sigaction(2).
        unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_fatal as *const () as usize;
            action.sa_flags = libc::SA_SIGINFO | libc::SA_ONSTACK;
            libc::sigemptyset(&mut action.sa_mask);
            let mut old: libc::sigaction = std::mem::zeroed();
            if libc::sigaction(sig, &action, &mut old) == 0 {
                previous.push((sig, old));
            }
        }
    }
    let _ = PREVIOUS.set(previous);
}
