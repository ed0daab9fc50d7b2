//! A writer that keeps its first error: for long recordings (`replay --record`, `--record-bag`)
//! written through libraries that either log every failed write and carry on (the Foxglove SDK: one
//! warning per message on a full disk) or are left in a broken state by one (the `mcap` writer,
//! whose later flush then fails on its own bookkeeping). The first error is kept, with its cause
//! ("No space left on device"), every write after it is dropped, and the caller asks
//! [`FirstError::get`] after each message and abandons the recording once.

use std::io::{Seek, SeekFrom, Write};
use std::sync::{Arc, Mutex};

/// The first error a [`GuardedWriter`] met, shared with whoever checks it.
#[derive(Debug, Clone, Default)]
pub struct FirstError(Arc<Mutex<Option<String>>>);

impl FirstError {
    /// The first failed write's error, in words; `None` while every write succeeded.
    pub fn get(&self) -> Option<String> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// `inner` behind [`FirstError`]: after the first failed write, seek or flush, every call
/// succeeds without touching `inner` (a recording that failed is abandoned whole, never half kept).
/// Positions stay consistent after it (writes move on, seeks land where asked), since writers that
/// seek compute offsets from them.
#[derive(Debug)]
pub struct GuardedWriter<W> {
    inner: W,
    error: FirstError,
    /// Where the next byte goes, and the furthest byte written.
    position: u64,
    len: u64,
}

impl<W> GuardedWriter<W> {
    /// Guard `inner`; the [`FirstError`] reports its first failure.
    pub fn new(inner: W) -> (Self, FirstError) {
        let error = FirstError::default();
        (
            Self {
                inner,
                error: error.clone(),
                position: 0,
                len: 0,
            },
            error,
        )
    }

    /// Run `f` on `inner` unless a call failed before; `false` when it did not run or failed now.
    /// The inner writer (to flush and sync it after the last write, say).
    pub fn into_inner(self) -> W {
        self.inner
    }

    /// Run `f` on `inner` unless a call failed before; keep its error as the first one.
    pub fn run(&mut self, f: impl FnOnce(&mut W) -> std::io::Result<()>) {
        self.guard(f);
    }

    fn guard(&mut self, f: impl FnOnce(&mut W) -> std::io::Result<()>) -> bool {
        let mut first = self.error.0.lock().unwrap_or_else(|e| e.into_inner());
        if first.is_some() {
            return false;
        }
        f(&mut self.inner)
            .map_err(|e| *first = Some(e.to_string()))
            .is_ok()
    }
}

impl<W: Write> Write for GuardedWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.guard(|w| w.write_all(buf));
        self.position += buf.len() as u64;
        self.len = self.len.max(self.position);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.guard(|w| w.flush());
        Ok(())
    }
}

impl<W: Seek> Seek for GuardedWriter<W> {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        let mut landed = None;
        self.guard(|w| {
            landed = Some(w.seek(pos)?);
            Ok(())
        });
        let offset = |base: u64, d: i64| base.checked_add_signed(d);
        self.position = landed
            .or(match pos {
                SeekFrom::Start(x) => Some(x),
                SeekFrom::Current(d) => offset(self.position, d),
                SeekFrom::End(d) => offset(self.len, d),
            })
            .ok_or_else(|| std::io::Error::from(std::io::ErrorKind::InvalidInput))?;
        Ok(self.position)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Takes `room` bytes, then fails as a full disk does.
    struct Disk {
        room: usize,
        kept: Vec<u8>,
    }

    impl Write for Disk {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            if self.kept.len() + buf.len() > self.room {
                return Err(std::io::Error::from_raw_os_error(28));
            }
            self.kept.extend_from_slice(buf);
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn the_first_error_is_kept_and_later_writes_are_dropped() {
        let (mut w, error) = GuardedWriter::new(Disk {
            room: 10,
            kept: Vec::new(),
        });
        w.write_all(b"12345678").unwrap();
        assert_eq!(error.get(), None);
        // The write that does not fit fails inside; the caller sees it through `error`.
        w.write_all(b"abc").unwrap();
        let e = error.get().unwrap();
        assert!(e.contains("No space left on device"), "{e}");
        // Nothing after it reaches the disk, even what would fit.
        w.write_all(b"9").unwrap();
        w.flush().unwrap();
        assert_eq!(w.inner.kept, b"12345678");
        assert_eq!(error.get().unwrap(), e);
    }

    #[test]
    fn positions_stay_consistent_after_the_failure() {
        let (mut w, error) = GuardedWriter::new(std::io::Cursor::new(Vec::new()));
        w.write_all(b"header").unwrap();
        assert_eq!(w.stream_position().unwrap(), 6);
        // Break the inner writer's seek: a position before the start.
        assert!(w.seek(SeekFrom::Current(-100)).is_err());
        assert!(error.get().is_some());
        // From here writes and seeks are counted, not done: offsets computed from them hold.
        w.write_all(b"0123456789").unwrap();
        assert_eq!(w.stream_position().unwrap(), 16);
        assert_eq!(w.seek(SeekFrom::Start(2)).unwrap(), 2);
        assert_eq!(w.seek(SeekFrom::End(-1)).unwrap(), 15);
        assert_eq!(w.inner.get_ref(), b"header");
    }
}
