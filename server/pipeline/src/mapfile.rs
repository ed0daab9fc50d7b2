//! The map file: one versioned file with checksummed sections, written atomically, read in bulk.
//!
//! Layout (all integers little-endian):
//! ```text
//! "PNTRMAP\0"  u32 format version
//! section*     [u8; 4] tag, u64 payload length, payload, u64 FNV-1a of the payload
//!   HEAD  the MapHeader as JSON (preset, model identities, intrinsics, scenes)
//!   IMGS  u64 image count, then per image: u64 record length, record (pose, keypoints, descriptors,
//!         3D points, instances, and since version 2 the verification thumbnail: u32 width, u32 height,
//!         f64 fx fy cx cy, u16 depth in mm, u8 grey), and since version 3 the image's camera: f64 fx fy
//!         cx cy, f64 k1 k2 p1 p2 k3, u32 width, u32 height (version 2 images take the header's camera),
//!         and since version 4 the recording's stamp: f64 seconds, NaN for none, and since version 5
//!         the refinement's finer depth: u8 0 (none) or 1, then a thumbnail as above
//!   RETR  the retrieval stage (codebook or vocabulary, and the faiss index or BoW vectors)
//!   END!  empty: a file without it was cut short
//! ```
//! Writing goes to `<file>.partial-<pid>`, is fsynced, then renamed over the target, so an interrupted
//! build never leaves a half-written map where a good one was. Reading streams the image records
//! through one reusable buffer, checking each section's checksum, so loading needs no second copy of
//! the map in memory; every problem is reported with the file name and the section.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use half::f16;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use pntr_core::bytes::{fnv1a_update, Reader, Writer, FNV1A_START};
use pntr_retrieval::global::Retriever;
use pntr_retrieval::onnx_global::OnnxGlobal;

use crate::map::{Map, MapHeader, MapImage};
use crate::verify::Thumb;
use crate::PipelineError;

const MAGIC: &[u8; 8] = b"PNTRMAP\0";
/// The map format version this build writes.
pub const FORMAT_VERSION: u32 = 5;
/// The oldest map format version this build reads (version 2 lacks per-image cameras).
pub const OLDEST_READABLE_VERSION: u32 = 2;

fn io(path: &Path) -> impl Fn(std::io::Error) -> PipelineError + '_ {
    move |e| PipelineError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

fn bad(path: &Path, message: String) -> PipelineError {
    PipelineError::MapFile {
        path: path.to_path_buf(),
        message,
    }
}

/// A writer that checksums what passes through.
struct Hashing<W> {
    inner: W,
    state: u64,
    written: u64,
}

impl<W: Write> Hashing<W> {
    fn put(&mut self, b: &[u8]) -> std::io::Result<()> {
        self.state = fnv1a_update(self.state, b);
        self.written += b.len() as u64;
        self.inner.write_all(b)
    }
}

fn encode_image(im: &MapImage, w: &mut Writer) {
    w.str(&im.id);
    w.u32(im.scene);
    w.u32(im.point);
    let t = im.world_from_camera.translation.vector;
    let q = im.world_from_camera.rotation.quaternion();
    for v in [t.x, t.y, t.z, q.w, q.i, q.j, q.k] {
        w.f64(v);
    }
    w.u32(im.image_size.0);
    w.u32(im.image_size.1);
    let n = im.keypoints.len();
    w.u32(n as u32);
    w.u32(im.dim as u32);
    for kp in &im.keypoints {
        w.f32(kp[0]);
        w.f32(kp[1]);
    }
    for s in &im.scores {
        w.f32(*s);
    }
    for d in &im.descriptors {
        w.raw(&d.to_bits().to_le_bytes());
    }
    w.u32(im.binary.len() as u32);
    for b in &im.binary {
        w.raw(b);
    }
    for p in &im.points {
        for v in p {
            w.f32(*v);
        }
    }
    for i in &im.instances {
        w.u32(*i);
    }
    encode_thumb(w, &im.thumb);
    let k = &im.camera;
    for v in [k.fx, k.fy, k.cx, k.cy].iter().chain(&k.distortion) {
        w.f64(*v);
    }
    w.u32(k.width);
    w.u32(k.height);
    w.f64(im.stamp.unwrap_or(f64::NAN));
    match &im.fine {
        Some(t) => {
            w.raw(&[1]);
            encode_thumb(w, t);
        }
        None => w.raw(&[0]),
    }
}

fn encode_thumb(w: &mut Writer, t: &Thumb) {
    w.u32(t.width);
    w.u32(t.height);
    for v in [
        t.intrinsics.fx,
        t.intrinsics.fy,
        t.intrinsics.cx,
        t.intrinsics.cy,
    ] {
        w.f64(v);
    }
    for d in &t.depth_mm {
        w.raw(&d.to_le_bytes());
    }
    w.raw(&t.gray);
}

fn decode_image(
    bytes: &[u8],
    index: usize,
    version: u32,
    header_camera: &pntr_core::Intrinsics,
) -> Result<MapImage, String> {
    let what = format!("image record {index}");
    let mut r = Reader::new(bytes, &what);
    let e = |x: pntr_core::bytes::BytesError| x.to_string();
    let id = r.str().map_err(e)?;
    let scene = r.u32().map_err(e)?;
    let point = r.u32().map_err(e)?;
    let mut v = [0f64; 7];
    for x in &mut v {
        *x = r.f64().map_err(e)?;
    }
    if v.iter().any(|x| !x.is_finite()) {
        return Err(format!("{what} ({id}): pose is not finite"));
    }
    let q = Quaternion::new(v[3], v[4], v[5], v[6]);
    if (q.norm() - 1.0).abs() > 1e-3 {
        return Err(format!("{what} ({id}): rotation is not a unit quaternion"));
    }
    // A rotation unit to rounding (one carried by a transform, as a merge does) is kept as it was
    // written, so a map read and written again is the same file; a looser one is normalised.
    let rotation = if (q.norm() - 1.0).abs() <= 1e-12 {
        UnitQuaternion::new_unchecked(q)
    } else {
        UnitQuaternion::from_quaternion(q)
    };
    let world_from_camera = Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), rotation);
    let image_size = (r.u32().map_err(e)?, r.u32().map_err(e)?);
    let n = r.u32().map_err(e)? as usize;
    let dim = r.u32().map_err(e)? as usize;
    // Every per-keypoint array must fit in what is left before anything is allocated.
    let need = n
        .checked_mul(8 + 4 + 12 + 4 + 2 * dim)
        .filter(|&b| b <= r.remaining())
        .ok_or_else(|| format!("{what} ({id}): {n} keypoints of dim {dim} do not fit"))?;
    let _ = need;
    let mut keypoints = Vec::with_capacity(n);
    for _ in 0..n {
        keypoints.push([r.f32().map_err(e)?, r.f32().map_err(e)?]);
    }
    let scores = (0..n)
        .map(|_| r.f32())
        .collect::<Result<Vec<_>, _>>()
        .map_err(e)?;
    let descriptors = r
        .take(n * dim * 2)
        .map_err(e)?
        .chunks_exact(2)
        .map(|c| f16::from_bits(u16::from_le_bytes([c[0], c[1]])))
        .collect();
    let nb = r.u32().map_err(e)? as usize;
    if nb != 0 && nb != n {
        return Err(format!(
            "{what} ({id}): {nb} binary descriptors for {n} keypoints"
        ));
    }
    let binary = r
        .take(nb * 32)
        .map_err(e)?
        .chunks_exact(32)
        .map(|c| c.try_into().expect("32 bytes"))
        .collect();
    let mut points = Vec::with_capacity(n);
    for _ in 0..n {
        points.push([
            r.f32().map_err(e)?,
            r.f32().map_err(e)?,
            r.f32().map_err(e)?,
        ]);
    }
    let instances = (0..n)
        .map(|_| r.u32())
        .collect::<Result<Vec<_>, _>>()
        .map_err(e)?;
    let thumb = decode_thumb(&mut r).map_err(|m| format!("{what} ({id}): thumbnail: {m}"))?;
    let camera = if version >= 3 {
        decode_camera(&mut r).map_err(|m| format!("{what} ({id}): camera: {m}"))?
    } else {
        *header_camera
    };
    let stamp = if version >= 4 {
        Some(r.f64().map_err(e)?).filter(|s| s.is_finite())
    } else {
        None
    };
    let fine = if version >= 5 {
        match r.take(1).map_err(e)?[0] {
            0 => None,
            1 => Some(decode_thumb(&mut r).map_err(|m| format!("{what} ({id}): fine depth: {m}"))?),
            other => return Err(format!("{what} ({id}): fine depth flag {other} (0 or 1)")),
        }
    } else {
        None
    };
    r.finish().map_err(e)?;
    if keypoints.iter().flatten().any(|x: &f32| !x.is_finite()) {
        return Err(format!("{what} ({id}): a keypoint is not finite"));
    }
    Ok(MapImage {
        id,
        scene,
        point,
        world_from_camera,
        stamp,
        keypoints,
        scores,
        descriptors,
        dim,
        binary,
        points,
        instances,
        image_size,
        camera,
        thumb,
        fine,
    })
}

fn decode_camera(r: &mut Reader) -> Result<pntr_core::Intrinsics, String> {
    let e = |x: pntr_core::bytes::BytesError| x.to_string();
    let mut v = [0f64; 9];
    for x in &mut v {
        *x = r.f64().map_err(e)?;
    }
    let k = pntr_core::Intrinsics {
        fx: v[0],
        fy: v[1],
        cx: v[2],
        cy: v[3],
        distortion: [v[4], v[5], v[6], v[7], v[8]],
        width: r.u32().map_err(e)?,
        height: r.u32().map_err(e)?,
    };
    k.validate().map_err(|x| x.to_string())?;
    Ok(k)
}

fn decode_thumb(r: &mut Reader) -> Result<Thumb, String> {
    let e = |x: pntr_core::bytes::BytesError| x.to_string();
    let (width, height) = (r.u32().map_err(e)?, r.u32().map_err(e)?);
    let mut k = [0f64; 4];
    for x in &mut k {
        *x = r.f64().map_err(e)?;
    }
    if width == 0 || height == 0 || width > 1024 || height > 1024 {
        return Err(format!("size {width}x{height} (1..1024 a side)"));
    }
    if !(k.iter().all(|v| v.is_finite()) && k[0] > 0.0 && k[1] > 0.0) {
        return Err(format!("intrinsics {k:?}"));
    }
    let n = (width * height) as usize;
    let depth_mm = r
        .take(n * 2)
        .map_err(e)?
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    let gray = r.take(n).map_err(e)?.to_vec();
    Ok(Thumb {
        width,
        height,
        intrinsics: pntr_core::Intrinsics {
            fx: k[0],
            fy: k[1],
            cx: k[2],
            cy: k[3],
            width,
            height,
            distortion: [0.0; 5],
        },
        depth_mm,
        gray,
    })
}

/// Write `map` to `path` atomically (temporary name, fsync, rename).
pub fn save(map: &Map, path: &Path) -> Result<(), PipelineError> {
    let tmp = PathBuf::from(format!("{}.partial-{}", path.display(), std::process::id()));
    let result = write_to(map, &tmp).and_then(|_| std::fs::rename(&tmp, path).map_err(io(path)));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// What `path` is when a map cannot be read from it: "no such file", "a folder", "a FIFO (named
/// pipe)", "a character device" (`/dev/zero`), "a block device", "a socket"; `None` for a regular
/// file or a link to one (and when the path cannot be examined: opening it then says why). Checked
/// before a map is opened, because reading a FIFO waits for a writer and a device never ends.
pub fn not_a_regular_file(path: &Path) -> Option<&'static str> {
    let kind = match std::fs::metadata(path) {
        Ok(m) => m.file_type(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Some("no such file"),
        Err(_) => return None,
    };
    if kind.is_file() {
        return None;
    }
    if kind.is_dir() {
        return Some("a folder");
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_fifo() {
            return Some("a FIFO (named pipe)");
        }
        if kind.is_char_device() {
            return Some("a character device");
        }
        if kind.is_block_device() {
            return Some("a block device");
        }
        if kind.is_socket() {
            return Some("a socket");
        }
    }
    Some("not a regular file")
}

/// Open a map file for reading, refusing what is not a regular file by what it is.
fn open_map(path: &Path) -> Result<File, PipelineError> {
    if let Some(what) = not_a_regular_file(path) {
        return Err(bad(path, not_a_map_file(what)));
    }
    File::open(path).map_err(io(path))
}

/// The sentence for a path that is not a regular file ([`not_a_regular_file`]'s answer).
pub fn not_a_map_file(what: &str) -> String {
    if what == "no such file" {
        what.to_string()
    } else {
        format!("{what}, not a map file (give the file `pntr build-db --out` wrote)")
    }
}

fn write_to(map: &Map, path: &Path) -> Result<(), PipelineError> {
    let file = File::create(path).map_err(io(path))?;
    let mut out = BufWriter::with_capacity(1 << 20, file);
    out.write_all(MAGIC).map_err(io(path))?;
    out.write_all(&FORMAT_VERSION.to_le_bytes())
        .map_err(io(path))?;
    let small = |out: &mut BufWriter<File>, tag: &[u8; 4], payload: &[u8]| {
        out.write_all(tag)?;
        out.write_all(&(payload.len() as u64).to_le_bytes())?;
        out.write_all(payload)?;
        out.write_all(&pntr_core::bytes::fnv1a(payload).to_le_bytes())
    };
    let head =
        serde_json::to_vec_pretty(&map.header).map_err(|e| bad(path, format!("header: {e}")))?;
    small(&mut out, b"HEAD", &head).map_err(io(path))?;
    // IMGS: streamed, length patched afterwards.
    out.write_all(b"IMGS").map_err(io(path))?;
    let len_at = out.stream_position().map_err(io(path))?;
    out.write_all(&0u64.to_le_bytes()).map_err(io(path))?;
    let mut h = Hashing {
        inner: out,
        state: FNV1A_START,
        written: 0,
    };
    h.put(&(map.images.len() as u64).to_le_bytes())
        .map_err(io(path))?;
    let mut w = Writer::new();
    for (i, im) in map.images.iter().enumerate() {
        w.bytes.clear();
        encode_image(im, &mut w);
        // The reader's own checks on every record: a map the server would refuse is never written.
        decode_image(&w.bytes, i, FORMAT_VERSION, &map.header.intrinsics).map_err(|m| {
            bad(
                path,
                format!("refusing to write a map that could not be loaded: {m}"),
            )
        })?;
        h.put(&(w.bytes.len() as u64).to_le_bytes())
            .map_err(io(path))?;
        h.put(&w.bytes).map_err(io(path))?;
    }
    let (mut out, state, written) = (h.inner, h.state, h.written);
    out.write_all(&state.to_le_bytes()).map_err(io(path))?;
    let end = out.stream_position().map_err(io(path))?;
    out.seek(SeekFrom::Start(len_at)).map_err(io(path))?;
    out.write_all(&written.to_le_bytes()).map_err(io(path))?;
    out.seek(SeekFrom::Start(end)).map_err(io(path))?;
    let retr = map.retriever.to_bytes()?;
    small(&mut out, b"RETR", &retr).map_err(io(path))?;
    small(&mut out, b"END!", &[]).map_err(io(path))?;
    let file = out.into_inner().map_err(|e| io(path)(e.into_error()))?;
    file.sync_all().map_err(io(path))
}

/// Read only the header of a map file (fast: for `pntr info`-style listings and start-up checks).
pub fn read_header(path: &Path) -> Result<MapHeader, PipelineError> {
    let mut r = BufReader::new(open_map(path)?);
    check_magic(&mut r, path)?;
    let (tag, payload) = small_section(&mut r, path)?;
    if &tag != b"HEAD" {
        return Err(bad(path, "the first section is not HEAD".into()));
    }
    parse_header(&payload, path)
}

/// The ids of a map file's images, in order, read from the start of each image record and seeking
/// past the rest: milliseconds on a map of any size, where [`load`] reads and decodes every record.
/// For what a header alone cannot say (whether the map's own calibration was fitted for these
/// images: [`crate::calibration::MapCalibration::is_stale_for`]). The section's checksum is not
/// verified (the records are skipped, not read); [`load`] verifies it. Errors: as [`read_header`],
/// and a section or record that runs past the file.
pub fn read_image_ids(path: &Path) -> Result<Vec<String>, PipelineError> {
    let mut r = BufReader::new(open_map(path)?);
    check_magic(&mut r, path)?;
    let (tag, _) = small_section(&mut r, path)?;
    expect(&tag, b"HEAD", path)?;
    let (tag, len) = section_head(&mut r, path)?;
    expect(&tag, b"IMGS", path)?;
    let cut = || bad(path, "section IMGS: truncated (file cut short?)".into());
    let mut word = [0u8; 8];
    r.read_exact(&mut word).map_err(|_| cut())?;
    let count = u64::from_le_bytes(word);
    if count > len / 8 {
        return Err(bad(
            path,
            format!("section IMGS: {count} images cannot fit in {len} bytes"),
        ));
    }
    let mut ids = Vec::with_capacity(count as usize);
    let mut head = Vec::new();
    for i in 0..count as usize {
        r.read_exact(&mut word).map_err(|_| cut())?;
        let n = u64::from_le_bytes(word);
        if n > len {
            return Err(bad(
                path,
                format!("section IMGS: record {i} claims {n} bytes"),
            ));
        }
        // An id is a length-prefixed string at the record's start; ids are short.
        let take = n.min(64 * 1024);
        head.resize(take as usize, 0);
        r.read_exact(&mut head).map_err(|_| cut())?;
        let what = format!("image record {i}");
        let id = Reader::new(&head, &what)
            .str()
            .map_err(|e| bad(path, format!("section IMGS: {e}")))?;
        ids.push(id);
        r.seek_relative((n - take) as i64).map_err(io(path))?;
    }
    Ok(ids)
}

/// Check the magic and return the format version.
fn check_magic(r: &mut impl Read, path: &Path) -> Result<u32, PipelineError> {
    let mut m = [0u8; 12];
    r.read_exact(&mut m)
        .map_err(|_| bad(path, "too short to be a pntr map".into()))?;
    if &m[..8] != MAGIC {
        return Err(bad(path, "not a pntr map file (bad magic)".into()));
    }
    let v = u32::from_le_bytes(m[8..12].try_into().expect("4 bytes"));
    if !(OLDEST_READABLE_VERSION..=FORMAT_VERSION).contains(&v) {
        return Err(bad(
            path,
            format!("map format version {v}; this build reads versions {OLDEST_READABLE_VERSION} to {FORMAT_VERSION} (rebuild the map with `pntr build-db`)"),
        ));
    }
    Ok(v)
}

fn section_head(r: &mut impl Read, path: &Path) -> Result<([u8; 4], u64), PipelineError> {
    let mut h = [0u8; 12];
    r.read_exact(&mut h).map_err(|_| {
        bad(
            path,
            "truncated: a section header is missing (file cut short?)".into(),
        )
    })?;
    let tag: [u8; 4] = h[..4].try_into().expect("4 bytes");
    Ok((tag, u64::from_le_bytes(h[4..].try_into().expect("8 bytes"))))
}

fn tag_name(t: &[u8; 4]) -> String {
    String::from_utf8_lossy(t).into_owned()
}

fn read_sum(
    r: &mut impl Read,
    path: &Path,
    tag: &[u8; 4],
    state: u64,
) -> Result<(), PipelineError> {
    let mut s = [0u8; 8];
    r.read_exact(&mut s).map_err(|_| {
        bad(
            path,
            format!("section {}: truncated before its checksum", tag_name(tag)),
        )
    })?;
    if u64::from_le_bytes(s) != state {
        return Err(bad(
            path,
            format!(
                "section {}: checksum mismatch (the file is corrupted)",
                tag_name(tag)
            ),
        ));
    }
    Ok(())
}

fn small_section(r: &mut impl Read, path: &Path) -> Result<([u8; 4], Vec<u8>), PipelineError> {
    let (tag, len) = section_head(r, path)?;
    let mut payload = Vec::new();
    r.take(len).read_to_end(&mut payload).map_err(io(path))?;
    if payload.len() as u64 != len {
        return Err(bad(
            path,
            format!(
                "section {}: truncated ({} of {len} bytes)",
                tag_name(&tag),
                payload.len()
            ),
        ));
    }
    read_sum(r, path, &tag, pntr_core::bytes::fnv1a(&payload))?;
    Ok((tag, payload))
}

fn parse_header(payload: &[u8], path: &Path) -> Result<MapHeader, PipelineError> {
    let header: MapHeader =
        serde_json::from_slice(payload).map_err(|e| bad(path, format!("section HEAD: {e}")))?;
    if let Some(c) = &header.calibration {
        c.check(path)?;
    }
    Ok(header)
}

fn expect(tag: &[u8; 4], want: &[u8; 4], path: &Path) -> Result<(), PipelineError> {
    if tag != want {
        return Err(bad(
            path,
            format!(
                "expected section {} but found {}",
                tag_name(want),
                tag_name(tag)
            ),
        ));
    }
    Ok(())
}

/// Load a map, checking version, every checksum and every record. `onnx` loads the global model of a
/// map built with the `onnx` descriptor (given the descriptor length the map stores).
pub fn load(
    path: &Path,
    onnx: impl FnOnce(usize) -> Result<OnnxGlobal, pntr_retrieval::RetrievalError>,
) -> Result<Map, PipelineError> {
    let mut r = BufReader::with_capacity(1 << 20, open_map(path)?);
    let version = check_magic(&mut r, path)?;
    let (tag, head) = small_section(&mut r, path)?;
    expect(&tag, b"HEAD", path)?;
    let header = parse_header(&head, path)?;
    let mut content = fnv1a_update(FNV1A_START, &pntr_core::bytes::fnv1a(&head).to_le_bytes());
    let (tag, len) = section_head(&mut r, path)?;
    expect(&tag, b"IMGS", path)?;
    let file_len = std::fs::metadata(path).map_err(io(path))?.len();
    if len > file_len {
        return Err(bad(
            path,
            format!("section IMGS: claims {len} bytes, the file has {file_len}"),
        ));
    }
    let mut state = FNV1A_START;
    let mut read = 0u64;
    let mut buf = vec![0u8; 8];
    let mut next =
        |r: &mut BufReader<File>, buf: &mut Vec<u8>, n: usize| -> Result<(), PipelineError> {
            if read + n as u64 > len {
                return Err(bad(
                    path,
                    "section IMGS: a record runs past the section".into(),
                ));
            }
            buf.resize(n, 0);
            r.read_exact(buf)
                .map_err(|_| bad(path, "section IMGS: truncated (file cut short?)".into()))?;
            state = fnv1a_update(state, buf);
            read += n as u64;
            Ok(())
        };
    next(&mut r, &mut buf, 8)?;
    let count = u64::from_le_bytes(buf[..8].try_into().expect("8 bytes"));
    if count > len / 8 {
        return Err(bad(
            path,
            format!("section IMGS: {count} images cannot fit in {len} bytes"),
        ));
    }
    let mut images = Vec::with_capacity(count as usize);
    for i in 0..count as usize {
        next(&mut r, &mut buf, 8)?;
        let n = u64::from_le_bytes(buf[..8].try_into().expect("8 bytes"));
        if n > len {
            return Err(bad(
                path,
                format!("section IMGS: record {i} claims {n} bytes"),
            ));
        }
        next(&mut r, &mut buf, n as usize)?;
        images.push(
            decode_image(&buf, i, version, &header.intrinsics)
                .map_err(|m| bad(path, format!("section IMGS: {m}")))?,
        );
    }
    if read != len {
        return Err(bad(
            path,
            format!("section IMGS: {} bytes left unread", len - read),
        ));
    }
    read_sum(&mut r, path, b"IMGS", state)?;
    content = fnv1a_update(content, &state.to_le_bytes());
    let (tag, retr) = small_section(&mut r, path)?;
    expect(&tag, b"RETR", path)?;
    content = fnv1a_update(content, &pntr_core::bytes::fnv1a(&retr).to_le_bytes());
    let retriever =
        Retriever::from_bytes(&retr, onnx).map_err(|e| bad(path, format!("section RETR: {e}")))?;
    let (tag, _) = small_section(&mut r, path)?;
    expect(&tag, b"END!", path)?;
    if retriever.len() != images.len() {
        return Err(bad(
            path,
            format!(
                "retrieval holds {} images, the map {}",
                retriever.len(),
                images.len()
            ),
        ));
    }
    if let Some(im) = images
        .iter()
        .find(|im| im.scene as usize >= header.scenes.len().max(1))
    {
        return Err(bad(
            path,
            format!(
                "image {} names scene {} of {}",
                im.id,
                im.scene,
                header.scenes.len()
            ),
        ));
    }
    Ok(Map {
        header,
        images,
        retriever,
        checksum: content,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_scenes::room_view;

    /// One map image with two keypoints, its thumbnail, and a finer depth when `fine`.
    fn image(fine: bool) -> MapImage {
        let thumb = room_view(&Isometry3::identity());
        MapImage {
            id: "scene/point0/db0".into(),
            scene: 0,
            point: 0,
            world_from_camera: Isometry3::translation(1.0, 2.0, 3.0),
            stamp: Some(12.5),
            keypoints: vec![[10.0, 20.0], [30.5, 40.25]],
            scores: vec![0.5, 0.25],
            descriptors: vec![f16::from_f32(0.5); 2 * 4],
            dim: 4,
            binary: Vec::new(),
            points: vec![[0.1, 0.2, 1.5], [f32::NAN; 3]],
            instances: vec![0, 7],
            image_size: (256, 256),
            camera: pntr_core::Intrinsics::hpointloc(),
            fine: fine.then(|| thumb.clone()),
            thumb,
        }
    }

    fn encoded(im: &MapImage) -> Vec<u8> {
        let mut w = Writer::new();
        encode_image(im, &mut w);
        w.bytes
    }

    /// Compares by the fields that NaN points leave comparable.
    fn same(a: &MapImage, b: &MapImage) {
        assert_eq!(a.id, b.id);
        assert_eq!(a.world_from_camera, b.world_from_camera);
        assert_eq!(a.stamp, b.stamp);
        assert_eq!(a.keypoints, b.keypoints);
        assert_eq!(a.thumb, b.thumb);
        assert_eq!(a.fine, b.fine);
        assert_eq!(a.camera, b.camera);
    }

    #[test]
    fn a_record_read_and_written_again_is_the_same_bytes() {
        // A rotation composed with another (as a merge carries images into A's frame) is unit
        // only to rounding; reading must not renormalise it, or the file changes on every pass.
        let mut im = image(true);
        let rotation = (1..1000)
            .map(|i| {
                let a = i as f64 * 0.37;
                UnitQuaternion::from_quaternion(Quaternion::new(a.cos(), 0.3, a.sin(), -0.2))
            })
            .find(|r| r.quaternion().coords.norm() != 1.0)
            .expect("a normalised quaternion whose norm rounds off 1");
        im.world_from_camera = Isometry3::from_parts(im.world_from_camera.translation, rotation);
        let q = im.world_from_camera.rotation.quaternion().coords;
        assert_ne!(q.norm(), 1.0, "the case under test: unit only to rounding");
        let k = pntr_core::Intrinsics::hpointloc();
        let bytes = encoded(&im);
        let back = decode_image(&bytes, 0, FORMAT_VERSION, &k).unwrap();
        assert_eq!(encoded(&back), bytes);
        // One that is off by more is normalised as before.
        let mut loose = bytes.clone();
        let at = 8 + im.id.len() + 4 + 4 + 3 * 8; // id (u64 length + bytes), scene, point, t
        loose[at..at + 8].copy_from_slice(&(q.w * 1.0001).to_le_bytes());
        let back = decode_image(&loose, 0, FORMAT_VERSION, &k).unwrap();
        let n = back.world_from_camera.rotation.quaternion().coords.norm();
        assert!((n - 1.0).abs() < 1e-12, "{n}");
    }

    #[test]
    fn the_finer_depth_round_trips_and_older_records_read_without_it() {
        let k = pntr_core::Intrinsics::hpointloc();
        for fine in [false, true] {
            let im = image(fine);
            let back = decode_image(&encoded(&im), 0, FORMAT_VERSION, &k).unwrap();
            same(&im, &back);
        }
        // A version-4 record is a version-5 record without the finer depth's flag (and thumbnail):
        // read as such, it has none; read as version 5, it is refused as cut short, not misread.
        let mut v4 = encoded(&image(false));
        assert_eq!(
            v4.pop(),
            Some(0),
            "the flag of no finer depth is the record's last byte"
        );
        let back = decode_image(&v4, 0, 4, &k).unwrap();
        assert!(back.fine.is_none());
        same(&image(false), &back);
        assert!(decode_image(&v4, 0, FORMAT_VERSION, &k).is_err());
        // A flag that is neither 0 nor 1 names what is wrong.
        let mut bad = encoded(&image(false));
        *bad.last_mut().unwrap() = 7;
        let e = decode_image(&bad, 0, FORMAT_VERSION, &k).unwrap_err();
        assert!(e.contains("fine depth flag 7"), "{e}");
    }
}
