//! Validating, view-at-a-time reader of one Point file.

use std::path::{Path, PathBuf};

use hdf5::dataset::Layout;
use hdf5::types::{FloatSize, IntSize, TypeDescriptor};
use nalgebra::Isometry3;
use ndarray::{s, Array2, ArrayD};
use pntr_core::{pose_from_hpointloc, DepthMap, Intrinsics, LabelMap, RgbImage};

use crate::last_words::h5;
use crate::{DatasetError, PointRecord, Role, View};

/// Largest image side accepted (pixels). HPointLoc frames are 256x256; a header claiming more than
/// this is corrupt or not HPointLoc, and refusing it keeps a damaged file from asking for gigabytes.
pub const MAX_IMAGE_SIDE: usize = 8192;

/// Most views of one role accepted in one Point file (HPointLoc has 6 database views and a few dozen
/// queries per Point). Poses are read eagerly, so this bounds what opening a file allocates.
pub const MAX_VIEWS: usize = 100_000;

/// Longest instance-to-category table accepted (one byte per instance id).
const MAX_INSTANCES: usize = 1 << 24;

/// What element type a field must have.
#[derive(Clone, Copy)]
enum Expect {
    U8,
    Float,
    Int,
}

/// Validated shape information for one role's fields.
#[derive(Debug, Clone)]
struct RoleInfo {
    count: usize,
    width: u32,
    height: u32,
    camera: Intrinsics,
    has_semantic: bool,
    depth_has_channel: bool,
    semantic_has_channel: bool,
    world_from_camera: Vec<Isometry3<f64>>,
}

/// An open Point file whose fields have been checked. Poses are read eagerly (they are small);
/// images are read per view.
pub struct PointReader {
    path: PathBuf,
    file: hdf5::File,
    db: RoleInfo,
    query: RoleInfo,
}

impl std::fmt::Debug for PointReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PointReader")
            .field("path", &self.path)
            .field("db_size", &(self.db.width, self.db.height))
            .field("query_size", &(self.query.width, self.query.height))
            .field("db", &self.db.count)
            .field("queries", &self.query.count)
            .finish()
    }
}

fn h5err(path: &Path, field: &str) -> impl FnOnce(hdf5::Error) -> DatasetError {
    let path = path.to_path_buf();
    let field = field.to_string();
    move |e| DatasetError::field(&path, &field, format!("read failed: {e}"))
}

impl PointReader {
    /// Open `path` and validate every field HPointLoc defines.
    pub fn open(path: &Path) -> Result<Self, DatasetError> {
        if !path.is_file() {
            return Err(DatasetError::Open {
                path: path.to_path_buf(),
                message: "no such file".into(),
            });
        }
        let file = h5(path, "the file's structure", || hdf5::File::open(path)).map_err(|e| {
            DatasetError::Open {
                path: path.to_path_buf(),
                message: e.to_string(),
            }
        })?;
        let db = Self::validate_role(path, &file, Role::Database)?;
        let query = Self::validate_role(path, &file, Role::Query)?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
            db,
            query,
        })
    }

    fn dataset(path: &Path, file: &hdf5::File, field: &str) -> Result<hdf5::Dataset, DatasetError> {
        h5(path, field, || file.dataset(field)).map_err(|e| {
            if h5(path, field, || file.link_exists(field)) {
                DatasetError::field(path, field, format!("unreadable: {e}"))
            } else {
                DatasetError::field(path, field, "missing")
            }
        })
    }

    fn check_dtype(
        path: &Path,
        ds: &hdf5::Dataset,
        field: &str,
        expect: Expect,
    ) -> Result<(), DatasetError> {
        let desc = h5(path, field, || ds.dtype().and_then(|t| t.to_descriptor()))
            .map_err(|e| DatasetError::field(path, field, format!("unreadable dtype: {e}")))?;
        let ok = match expect {
            Expect::U8 => matches!(desc, TypeDescriptor::Unsigned(IntSize::U1)),
            Expect::Float => matches!(
                desc,
                TypeDescriptor::Float(FloatSize::U4) | TypeDescriptor::Float(FloatSize::U8)
            ),
            Expect::Int => matches!(
                desc,
                TypeDescriptor::Unsigned(IntSize::U1 | IntSize::U2 | IntSize::U4)
                    | TypeDescriptor::Integer(IntSize::U1 | IntSize::U2 | IntSize::U4)
            ),
        };
        if !ok {
            let want = match expect {
                Expect::U8 => "uint8",
                Expect::Float => "float32 or float64",
                Expect::Int => "an integer type of at most 32 bits",
            };
            return Err(DatasetError::field(
                path,
                field,
                format!("dtype is {desc:?}, expected {want}"),
            ));
        }
        h5(path, field, || Self::check_storage(path, ds, field))
    }

    /// Structural checks HDF5 1.10 left out and crashed without (both found by fuzzing): the bytes a
    /// compact or contiguous dataset stores must be exactly what its shape and type need and lie
    /// inside the file; every chunk of a chunked dataset must start on a chunk boundary inside the
    /// extent and lie inside the file. A file failing them is refused before any data is read.
    fn check_storage(path: &Path, ds: &hdf5::Dataset, field: &str) -> Result<(), DatasetError> {
        let bad = |problem: String| DatasetError::field(path, field, problem);
        let file_len = std::fs::metadata(path)
            .map_err(|e| bad(format!("cannot stat the file: {e}")))?
            .len();
        let elem = ds
            .dtype()
            .map_err(|e| bad(format!("unreadable dtype: {e}")))?
            .size() as u64;
        let shape = ds.shape();
        let need = shape
            .iter()
            .try_fold(elem, |acc, &d| acc.checked_mul(d as u64))
            .ok_or_else(|| bad(format!("shape {shape:?} overflows")))?;
        match ds.layout() {
            Layout::Compact | Layout::Contiguous => {
                let stored = ds.storage_size();
                if stored != need {
                    return Err(bad(format!(
                        "stores {stored} bytes where shape {shape:?} needs {need}: damaged file"
                    )));
                }
                if let Some(offset) = ds.offset() {
                    if offset.checked_add(stored).is_none_or(|end| end > file_len) {
                        return Err(bad(format!(
                            "data at byte {offset} (+{stored}) lies past the end of the file ({file_len} bytes)"
                        )));
                    }
                }
            }
            Layout::Chunked => {
                let chunk = ds.chunk().unwrap_or_default();
                // A fixed-size dataset's chunks may not exceed its extent (HDF5's own rule, which
                // 1.10 did not re-check when reading: a chunk of [1, 6, 8, 1025] over [2, 6, 8, 1]
                // made it copy past its buffer).
                let fits =
                    ds.is_resizable() || chunk.iter().zip(&shape).all(|(&c, &d)| c <= d.max(1));
                if chunk.len() != shape.len() || chunk.contains(&0) || !fits {
                    return Err(bad(format!(
                        "chunk shape {chunk:?} does not fit shape {shape:?}: damaged file"
                    )));
                }
                let most: usize = shape
                    .iter()
                    .zip(&chunk)
                    .map(|(d, c)| d.div_ceil(*c))
                    .product();
                let count = ds.num_chunks().unwrap_or(0);
                if count > most {
                    return Err(bad(format!("{count} chunks where the shape allows {most}")));
                }
                for i in 0..count {
                    let info = ds
                        .chunk_info(i)
                        .ok_or_else(|| bad(format!("chunk {i} is unreadable")))?;
                    let aligned = info
                        .offset
                        .iter()
                        .zip(shape.iter().zip(&chunk))
                        .all(|(&o, (&d, &c))| (o as usize) < d && (o as usize) % c == 0);
                    let inside = info
                        .addr
                        .checked_add(info.size)
                        .is_some_and(|end| end <= file_len);
                    if info.offset.len() != shape.len() || !aligned || !inside {
                        return Err(bad(format!(
                            "chunk {i} (offset {:?}, {} bytes at {}) is outside the dataset or the file",
                            info.offset, info.size, info.addr
                        )));
                    }
                }
            }
            #[allow(unreachable_patterns)]
            other => return Err(bad(format!("unsupported storage layout {other:?}"))),
        }
        Ok(())
    }

    fn validate_role(path: &Path, file: &hdf5::File, role: Role) -> Result<RoleInfo, DatasetError> {
        let f_rgb = role.field("rgb");
        let f_depth = role.field("depth");
        let f_sem = role.field("semantic");
        let f_gps = role.field("gps");
        let f_quat = role.field("quat");

        let rgb = Self::dataset(path, file, &f_rgb)?;
        Self::check_dtype(path, &rgb, &f_rgb, Expect::U8)?;
        let shape = rgb.shape();
        if shape.len() != 4 || shape[3] != 3 || shape[1] == 0 || shape[2] == 0 {
            return Err(DatasetError::field(
                path,
                &f_rgb,
                format!("shape {shape:?}, expected (N, H, W, 3)"),
            ));
        }
        let (n, h, w) = (shape[0], shape[1], shape[2]);
        if h > MAX_IMAGE_SIDE || w > MAX_IMAGE_SIDE || n > MAX_VIEWS {
            return Err(DatasetError::field(
                path,
                &f_rgb,
                format!(
                    "shape {shape:?} is beyond the reader's limits ({MAX_VIEWS} views, \
                     {MAX_IMAGE_SIDE} pixels a side): the file is damaged or not HPointLoc"
                ),
            ));
        }

        let depth = Self::dataset(path, file, &f_depth)?;
        Self::check_dtype(path, &depth, &f_depth, Expect::Float)?;
        let dshape = depth.shape();
        let depth_has_channel = match dshape.as_slice() {
            [dn, dh, dw] if (*dn, *dh, *dw) == (n, h, w) => false,
            [dn, dh, dw, 1] if (*dn, *dh, *dw) == (n, h, w) => true,
            _ => {
                return Err(DatasetError::field(
                    path,
                    &f_depth,
                    format!("shape {dshape:?}, expected ({n}, {h}, {w}, 1) or ({n}, {h}, {w}) to match `{f_rgb}`"),
                ))
            }
        };

        let (has_semantic, semantic_has_channel) = match h5(path, &f_sem, || file.dataset(&f_sem)) {
            Err(_) => (false, false),
            Ok(sem) => {
                Self::check_dtype(path, &sem, &f_sem, Expect::Int)?;
                let sshape = sem.shape();
                let ch = match sshape.as_slice() {
                    [sn, sh, sw] if (*sn, *sh, *sw) == (n, h, w) => false,
                    [sn, sh, sw, 1] if (*sn, *sh, *sw) == (n, h, w) => true,
                    _ => {
                        return Err(DatasetError::field(
                            path,
                            &f_sem,
                            format!(
                                "shape {sshape:?}, expected ({n}, {h}, {w}) or ({n}, {h}, {w}, 1)"
                            ),
                        ))
                    }
                };
                (true, ch)
            }
        };

        let gps = Self::read_table(path, file, &f_gps, n, 3)?;
        let quat = Self::read_table(path, file, &f_quat, n, 4)?;
        let mut world_from_camera = Vec::with_capacity(n);
        for i in 0..n {
            let g = [gps[[i, 0]], gps[[i, 1]], gps[[i, 2]]];
            let q = [quat[[i, 0]], quat[[i, 1]], quat[[i, 2]], quat[[i, 3]]];
            let pose = pose_from_hpointloc(g, q).map_err(|e| {
                DatasetError::field(path, &format!("{f_gps}/{f_quat}"), format!("row {i}: {e}"))
            })?;
            world_from_camera.push(pose);
        }
        let camera = Self::read_camera(path, file, role, w as u32, h as u32)?;
        Ok(RoleInfo {
            count: n,
            width: w as u32,
            height: h as u32,
            camera,
            has_semantic,
            depth_has_channel,
            semantic_has_channel,
            world_from_camera,
        })
    }

    /// The role's camera field, checked, or HPointLoc's 90-degree camera at the role's size.
    fn read_camera(
        path: &Path,
        file: &hdf5::File,
        role: Role,
        w: u32,
        h: u32,
    ) -> Result<Intrinsics, DatasetError> {
        let field = role.field("camera");
        let Ok(ds) = h5(path, &field, || file.dataset(&field)) else {
            return Ok(crate::default_camera(w, h));
        };
        Self::check_dtype(path, &ds, &field, Expect::Float)?;
        let shape = ds.shape();
        if shape != [4] && shape != [9] {
            return Err(DatasetError::field(
                path,
                &field,
                format!(
                    "shape {shape:?}, expected (4,) [fx, fy, cx, cy] or (9,) with k1 k2 p1 p2 k3"
                ),
            ));
        }
        let v = h5(path, &field, || ds.read_raw::<f64>()).map_err(h5err(path, &field))?;
        let mut distortion = [0.0; 5];
        if v.len() == 9 {
            distortion.copy_from_slice(&v[4..]);
        }
        let k = Intrinsics {
            fx: v[0],
            fy: v[1],
            cx: v[2],
            cy: v[3],
            width: w,
            height: h,
            distortion,
        };
        k.validate()
            .map_err(|e| DatasetError::field(path, &field, e.to_string()))?;
        Ok(k)
    }

    fn read_table(
        path: &Path,
        file: &hdf5::File,
        field: &str,
        rows: usize,
        cols: usize,
    ) -> Result<Array2<f64>, DatasetError> {
        let ds = Self::dataset(path, file, field)?;
        Self::check_dtype(path, &ds, field, Expect::Float)?;
        let shape = ds.shape();
        if shape != [rows, cols] {
            return Err(DatasetError::field(
                path,
                field,
                format!("shape {shape:?}, expected ({rows}, {cols})"),
            ));
        }
        h5(path, field, || ds.read_2d::<f64>()).map_err(h5err(path, field))
    }

    /// The file this reader reads.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Database image width in pixels.
    pub fn width(&self) -> u32 {
        self.db.width
    }

    /// Database image height in pixels.
    pub fn height(&self) -> u32 {
        self.db.height
    }

    /// (width, height) of the images of `role`.
    pub fn size(&self, role: Role) -> (u32, u32) {
        (self.info(role).width, self.info(role).height)
    }

    /// The camera of the images of `role`.
    pub fn camera(&self, role: Role) -> Intrinsics {
        self.info(role).camera
    }

    fn info(&self, role: Role) -> &RoleInfo {
        match role {
            Role::Database => &self.db,
            Role::Query => &self.query,
        }
    }

    /// Number of views of `role`.
    pub fn count(&self, role: Role) -> usize {
        self.info(role).count
    }

    /// Poses (`world_from_camera`, Habitat axes) of every view of `role`.
    pub fn poses(&self, role: Role) -> &[Isometry3<f64>] {
        &self.info(role).world_from_camera
    }

    fn read_frame<T: hdf5::H5Type>(&self, field: &str, i: usize) -> Result<Vec<T>, DatasetError> {
        let ds = Self::dataset(&self.path, &self.file, field)?;
        let arr: ArrayD<T> = h5(&self.path, field, || match ds.ndim() {
            3 => ds.read_slice(s![i, .., ..]),
            _ => ds.read_slice(s![i, .., .., ..]),
        })
        .map_err(h5err(&self.path, field))?;
        let (v, _) = arr.into_raw_vec_and_offset();
        Ok(v)
    }

    /// Read view `i` of `role`.
    pub fn view(&self, role: Role, i: usize) -> Result<View, DatasetError> {
        let info = self.info(role);
        if i >= info.count {
            return Err(DatasetError::field(
                &self.path,
                &role.field("rgb"),
                format!("view {i} requested, the file has {}", info.count),
            ));
        }
        let (w, h) = (info.width, info.height);
        let f_rgb = role.field("rgb");
        let rgb = RgbImage::new(w, h, self.read_frame::<u8>(&f_rgb, i)?)
            .map_err(|e| DatasetError::field(&self.path, &f_rgb, e.to_string()))?;
        let f_depth = role.field("depth");
        let raw = self.read_frame::<f32>(&f_depth, i)?;
        let depth = DepthMap::from_hpointloc(w, h, &raw)
            .map_err(|e| DatasetError::field(&self.path, &f_depth, e.to_string()))?;
        let semantic = if info.has_semantic {
            let f_sem = role.field("semantic");
            let labels = self.read_frame::<u32>(&f_sem, i)?;
            Some(
                LabelMap::new(w, h, labels)
                    .map_err(|e| DatasetError::field(&self.path, &f_sem, e.to_string()))?,
            )
        } else {
            None
        };
        let _ = (info.depth_has_channel, info.semantic_has_channel);
        Ok(View {
            world_from_camera: info.world_from_camera[i],
            rgb,
            depth,
            semantic,
            intrinsics: info.camera,
        })
    }

    /// The instance-to-category table (`semantic_category`), if the file has one.
    pub fn instance_categories(&self) -> Result<Option<Vec<u8>>, DatasetError> {
        let field = "semantic_category";
        match h5(&self.path, field, || self.file.dataset(field)) {
            Err(_) => Ok(None),
            Ok(ds) => {
                Self::check_dtype(&self.path, &ds, field, Expect::U8)?;
                if ds.ndim() != 1 || ds.size() > MAX_INSTANCES {
                    return Err(DatasetError::field(
                        &self.path,
                        field,
                        format!(
                            "shape {:?}, expected one dimension of at most {MAX_INSTANCES}",
                            ds.shape()
                        ),
                    ));
                }
                Ok(Some(
                    h5(&self.path, field, || ds.read_raw::<u8>())
                        .map_err(h5err(&self.path, field))?,
                ))
            }
        }
    }

    /// Read every view of the file.
    pub fn read_all(&self) -> Result<PointRecord, DatasetError> {
        let db = (0..self.db.count)
            .map(|i| self.view(Role::Database, i))
            .collect::<Result<_, _>>()?;
        let queries = (0..self.query.count)
            .map(|i| self.view(Role::Query, i))
            .collect::<Result<_, _>>()?;
        Ok(PointRecord {
            db,
            queries,
            instance_categories: self.instance_categories()?,
        })
    }
}
