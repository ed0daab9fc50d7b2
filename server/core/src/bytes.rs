//! Little-endian byte encoding for the binary sections of map files: a writer that appends and a
//! bounds-checked reader whose every failure says what was being read, so a truncated or corrupted
//! section becomes an error naming its part, never a panic or a huge allocation.

/// Appends little-endian values to a byte vector.
#[derive(Debug, Default, Clone)]
pub struct Writer {
    /// The bytes written so far.
    pub bytes: Vec<u8>,
}

impl Writer {
    /// An empty writer.
    pub fn new() -> Self {
        Self::default()
    }
    /// Append a u32.
    pub fn u32(&mut self, v: u32) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    /// Append a u64.
    pub fn u64(&mut self, v: u64) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    /// Append an f32.
    pub fn f32(&mut self, v: f32) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    /// Append an f64.
    pub fn f64(&mut self, v: f64) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    /// Append raw bytes.
    pub fn raw(&mut self, b: &[u8]) {
        self.bytes.extend_from_slice(b);
    }
    /// Append a length-prefixed (u64) byte string.
    pub fn blob(&mut self, b: &[u8]) {
        self.u64(b.len() as u64);
        self.raw(b);
    }
    /// Append a length-prefixed f32 slice.
    pub fn f32s(&mut self, v: &[f32]) {
        self.u64(v.len() as u64);
        for x in v {
            self.f32(*x);
        }
    }
    /// Append a length-prefixed UTF-8 string.
    pub fn str(&mut self, s: &str) {
        self.blob(s.as_bytes());
    }
}

/// Reads little-endian values, failing with a message naming `what` when the bytes run out.
#[derive(Debug)]
pub struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
    what: &'a str,
}

/// A read past the end, or bytes that do not form what was expected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{what}: {message}")]
pub struct BytesError {
    /// What was being read.
    pub what: String,
    /// What went wrong.
    pub message: String,
}

impl<'a> Reader<'a> {
    /// Read `bytes`, naming them `what` in errors.
    pub fn new(bytes: &'a [u8], what: &'a str) -> Self {
        Self {
            bytes,
            pos: 0,
            what,
        }
    }
    fn err(&self, message: String) -> BytesError {
        BytesError {
            what: self.what.to_string(),
            message,
        }
    }
    /// The next `n` bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8], BytesError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(self.err(format!(
                "truncated: {n} bytes wanted at offset {} of {}",
                self.pos,
                self.bytes.len()
            )));
        };
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    /// A u32.
    pub fn u32(&mut self) -> Result<u32, BytesError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    /// A u64.
    pub fn u64(&mut self) -> Result<u64, BytesError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
    /// An f32.
    pub fn f32(&mut self) -> Result<f32, BytesError> {
        Ok(f32::from_le_bytes(self.take(4)?.try_into().expect("4")))
    }
    /// An f64.
    pub fn f64(&mut self) -> Result<f64, BytesError> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().expect("8")))
    }
    /// A length-prefixed byte string.
    pub fn blob(&mut self) -> Result<&'a [u8], BytesError> {
        let n = self.u64()?;
        let n = usize::try_from(n).map_err(|_| self.err(format!("length {n}")))?;
        self.take(n)
    }
    /// A length-prefixed f32 slice (its length is checked against the bytes left before allocating).
    pub fn f32s(&mut self) -> Result<Vec<f32>, BytesError> {
        let n = self.u64()?;
        let bytes = n
            .checked_mul(4)
            .and_then(|b| usize::try_from(b).ok())
            .ok_or_else(|| self.err(format!("length {n}")))?;
        Ok(self
            .take(bytes)?
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4")))
            .collect())
    }
    /// A length-prefixed UTF-8 string.
    pub fn str(&mut self) -> Result<String, BytesError> {
        let b = self.blob()?;
        String::from_utf8(b.to_vec()).map_err(|_| self.err("a string is not UTF-8".into()))
    }
    /// Bytes not yet read.
    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }
    /// Fail unless every byte was read.
    pub fn finish(&self) -> Result<(), BytesError> {
        if self.pos == self.bytes.len() {
            Ok(())
        } else {
            Err(self.err(format!("{} unexpected trailing bytes", self.remaining())))
        }
    }
}

/// FNV-1a 64-bit: a fast checksum of sections (corruption detection, not security).
pub fn fnv1a(bytes: &[u8]) -> u64 {
    fnv1a_update(FNV1A_START, bytes)
}

/// The FNV-1a state before any byte.
pub const FNV1A_START: u64 = 0xcbf2_9ce4_8422_2325;

/// Continue an FNV-1a checksum over more bytes (for data read or written in pieces).
pub fn fnv1a_update(state: u64, bytes: &[u8]) -> u64 {
    bytes
        .iter()
        .fold(state, |h, &b| (h ^ b as u64).wrapping_mul(0x1000_0000_01b3))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_truncation() {
        let mut w = Writer::new();
        w.u32(7);
        w.f32s(&[1.5, -2.0]);
        w.str("xfeat");
        w.f64(0.25);
        let mut r = Reader::new(&w.bytes, "test");
        assert_eq!(r.u32().unwrap(), 7);
        assert_eq!(r.f32s().unwrap(), vec![1.5, -2.0]);
        assert_eq!(r.str().unwrap(), "xfeat");
        assert_eq!(r.f64().unwrap(), 0.25);
        r.finish().unwrap();
        let mut r = Reader::new(&w.bytes[..10], "section x");
        r.u32().unwrap();
        let e = r.f32s().unwrap_err().to_string();
        assert!(e.starts_with("section x: truncated"), "{e}");
        // A huge length prefix is refused without allocating.
        let mut w = Writer::new();
        w.u64(u64::MAX / 2);
        assert!(Reader::new(&w.bytes, "x").f32s().is_err());
    }
}
