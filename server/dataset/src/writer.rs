//! Writing one Point file in HPointLoc's layout, atomically.

use std::path::{Path, PathBuf};

use ndarray::{Array2, ArrayView2, ArrayView3, ArrayView4};
use pntr_core::pose_to_hpointloc;

use crate::{DatasetError, PointRecord, Role, View};

/// How to write.
#[derive(Debug, Clone, Copy)]
pub struct WriteOptions {
    /// gzip level for depth and labels (one chunk per frame); `None` writes every field contiguous.
    pub gzip_level: Option<u8>,
}

impl Default for WriteOptions {
    fn default() -> Self {
        // Level 1 shrinks depth and labels several-fold at little CPU cost; noisy RGB barely shrinks.
        Self {
            gzip_level: Some(1),
        }
    }
}

fn h5(path: &Path, field: &str) -> impl FnOnce(hdf5::Error) -> DatasetError {
    let path = path.to_path_buf();
    let field = field.to_string();
    move |e| DatasetError::Field {
        path,
        field,
        problem: format!("write failed: {e}"),
    }
}

/// Write `record` to `path` (parent folders are created). The data goes to a temporary file in the
/// same folder first and is renamed over `path` only when complete.
pub fn write_point(
    path: &Path,
    record: &PointRecord,
    opts: &WriteOptions,
) -> Result<(), DatasetError> {
    if record.db.is_empty() && record.queries.is_empty() {
        return Err(DatasetError::Layout {
            path: path.to_path_buf(),
            problem: "a Point needs at least one view".into(),
        });
    }
    for (role, views) in [("database", &record.db), ("query", &record.queries)] {
        let Some(first) = views.first() else {
            continue;
        };
        let (w, h) = (first.rgb.width, first.rgb.height);
        if let Some(v) = views.iter().find(|v| {
            (v.rgb.width, v.rgb.height) != (w, h)
                || (v.depth.width, v.depth.height) != (w, h)
                || v.intrinsics != first.intrinsics
        }) {
            return Err(DatasetError::Layout {
                path: path.to_path_buf(),
                problem: format!(
                    "all {role} views must be {w}x{h} with one camera; found rgb {}x{} depth {}x{} camera {:?}",
                    v.rgb.width, v.rgb.height, v.depth.width, v.depth.height, v.intrinsics
                ),
            });
        }
    }
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|source| DatasetError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let tmp = tmp_name(path);
    let result = write_file(&tmp, record, opts);
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, path).map_err(|source| {
        let _ = std::fs::remove_file(&tmp);
        DatasetError::Io {
            path: path.to_path_buf(),
            source,
        }
    })
}

fn tmp_name(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".partial-{}", std::process::id()));
    path.with_file_name(name)
}

fn write_file(tmp: &Path, record: &PointRecord, opts: &WriteOptions) -> Result<(), DatasetError> {
    let file = hdf5::File::create(tmp).map_err(|e| DatasetError::Open {
        path: tmp.to_path_buf(),
        message: e.to_string(),
    })?;
    // A role without views takes the other role's size (HDF5 needs a shape even for zero frames).
    let any = record
        .db
        .first()
        .or(record.queries.first())
        .expect("checked");
    for (role, views) in [(Role::Database, &record.db), (Role::Query, &record.queries)] {
        let v = views.first().unwrap_or(any);
        let (w, h) = (v.rgb.width as usize, v.rgb.height as usize);
        write_role(&file, tmp, role, views, w, h, opts)?;
        // HPointLoc's own camera is implied by the layout; any other is written for pntr's readers.
        if v.intrinsics != crate::default_camera(v.rgb.width, v.rgb.height) {
            let k = &v.intrinsics;
            let mut row = vec![k.fx, k.fy, k.cx, k.cy];
            if k.is_distorted() {
                row.extend_from_slice(&k.distortion);
            }
            let f = role.field("camera");
            file.new_dataset_builder()
                .with_data(row.as_slice())
                .create(f.as_str())
                .map_err(h5(tmp, &f))?;
        }
    }
    if let Some(table) = &record.instance_categories {
        file.new_dataset_builder()
            .with_data(table.as_slice())
            .create("semantic_category")
            .map_err(h5(tmp, "semantic_category"))?;
    }
    file.close().map_err(|e| DatasetError::Open {
        path: tmp.to_path_buf(),
        message: format!("close failed: {e}"),
    })
}

fn write_role(
    file: &hdf5::File,
    tmp: &Path,
    role: Role,
    views: &[View],
    w: usize,
    h: usize,
    opts: &WriteOptions,
) -> Result<(), DatasetError> {
    let n = views.len();
    let mut rgb = Vec::with_capacity(n * h * w * 3);
    let mut depth = Vec::with_capacity(n * h * w);
    let mut gps = Array2::<f32>::zeros((n, 3));
    let mut quat = Array2::<f32>::zeros((n, 4));
    for (i, v) in views.iter().enumerate() {
        rgb.extend_from_slice(&v.rgb.data);
        depth.extend(v.depth.to_hpointloc());
        let (g, q) = pose_to_hpointloc(&v.world_from_camera);
        for k in 0..3 {
            gps[[i, k]] = g[k] as f32;
        }
        for k in 0..4 {
            quat[[i, k]] = q[k] as f32;
        }
    }
    // Compression needs chunking, and a chunk cannot be larger than a fixed zero-length dataset.
    let gz = if n > 0 { opts.gzip_level } else { None };

    // RGB is chunked per frame but not compressed: sensor noise leaves gzip little to gain (about
    // 10%) for most of the write time.
    let f = role.field("rgb");
    let arr = ArrayView4::from_shape((n, h, w, 3), &rgb).expect("sized above");
    let b = file.new_dataset_builder().with_data(arr);
    match gz {
        Some(_) => b.chunk((1, h, w, 3)).create(f.as_str()),
        None => b.create(f.as_str()),
    }
    .map_err(h5(tmp, &f))?;

    let f = role.field("depth");
    let arr = ArrayView4::from_shape((n, h, w, 1), &depth).expect("sized above");
    let b = file.new_dataset_builder().with_data(arr);
    match gz {
        Some(l) => b
            .chunk((1, h, w, 1))
            .shuffle()
            .deflate(l)
            .create(f.as_str()),
        None => b.create(f.as_str()),
    }
    .map_err(h5(tmp, &f))?;

    let with_sem = views.iter().filter(|v| v.semantic.is_some()).count();
    if with_sem == n && n > 0 {
        let mut sem = Vec::with_capacity(n * h * w);
        for v in views {
            sem.extend_from_slice(&v.semantic.as_ref().expect("checked").data);
        }
        let f = role.field("semantic");
        let arr = ArrayView3::from_shape((n, h, w), &sem).expect("sized above");
        let b = file.new_dataset_builder().with_data(arr);
        match gz {
            Some(l) => b.chunk((1, h, w)).shuffle().deflate(l).create(f.as_str()),
            None => b.create(f.as_str()),
        }
        .map_err(h5(tmp, &f))?;
    } else if with_sem != 0 {
        return Err(DatasetError::field(
            tmp,
            &role.field("semantic"),
            format!("{with_sem} of {n} views have labels; all or none must"),
        ));
    }

    for (stem, table) in [("gps", gps.view()), ("quat", quat.view())] {
        let f = role.field(stem);
        let t: ArrayView2<f32> = table;
        file.new_dataset_builder()
            .with_data(t)
            .create(f.as_str())
            .map_err(h5(tmp, &f))?;
    }
    Ok(())
}
