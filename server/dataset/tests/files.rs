//! Reading and writing Point files: round trip, and every kind of bad input named by file and field.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use ndarray::{Array2, Array3, Array4};
use pntr_core::{DepthMap, LabelMap, RgbImage};
use pntr_dataset::{
    layout, write_point, DatasetIndex, PointReader, PointRecord, Role, View, WriteOptions,
};

const W: u32 = 8;
const H: u32 = 6;

fn view(seed: u32, with_labels: bool) -> View {
    let n = (W * H) as usize;
    let rgb = (0..n * 3)
        .map(|i| ((i as u32 * 7 + seed * 13) % 256) as u8)
        .collect();
    // Depths in metres, one invalid pixel; multiples of 1/8 m survive the /10 encoding in f32 closely.
    let depth = (0..n)
        .map(|i| {
            if i == 3 {
                0.0
            } else {
                0.5 + (i as f32 + seed as f32) * 0.125 % 9.0
            }
        })
        .collect();
    View {
        world_from_camera: Isometry3::from_parts(
            Translation3::new(seed as f64, 1.25, -(seed as f64) * 0.5),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), seed as f64 * 0.3),
        ),
        rgb: RgbImage::new(W, H, rgb).unwrap(),
        depth: DepthMap::from_metres(W, H, depth).unwrap(),
        semantic: with_labels
            .then(|| LabelMap::new(W, H, (0..n as u32).map(|i| i % 5 + seed).collect()).unwrap()),
        intrinsics: pntr_dataset::default_camera(W, H),
    }
}

fn record() -> PointRecord {
    PointRecord {
        db: (0..6).map(|i| view(i, true)).collect(),
        queries: (0..4).map(|i| view(10 + i, false)).collect(),
        instance_categories: Some(vec![0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15]),
    }
}

fn assert_close(a: &View, b: &View) {
    assert_eq!(a.rgb, b.rgb);
    assert_eq!(a.semantic, b.semantic);
    for (x, y) in a.depth.data.iter().zip(&b.depth.data) {
        assert!((x - y).abs() < 1e-5, "depth {x} vs {y}");
    }
    assert!(
        (a.world_from_camera.translation.vector - b.world_from_camera.translation.vector).norm()
            < 1e-5
    );
    assert!(
        a.world_from_camera
            .rotation
            .angle_to(&b.world_from_camera.rotation)
            < 1e-6
    );
}

#[test]
fn round_trip_through_the_layout() {
    let dir = tempfile::tempdir().unwrap();
    let rec = record();
    for gzip in [None, Some(1)] {
        let path = layout::point_path(dir.path(), "sceneA", 7);
        write_point(&path, &rec, &WriteOptions { gzip_level: gzip }).unwrap();
        let index = DatasetIndex::open(dir.path()).unwrap();
        assert_eq!(index.scenes.len(), 1);
        let scene = index.scene("sceneA").unwrap();
        assert_eq!(scene.points.len(), 1);
        assert_eq!(scene.points[0].index, 7);
        assert_eq!(scene.points[0].db_image_id(2), "sceneA/point7/db2");
        let r = scene.points[0].open().unwrap();
        assert_eq!((r.width(), r.height()), (W, H));
        assert_eq!(r.count(Role::Database), 6);
        assert_eq!(r.count(Role::Query), 4);
        let back = r.read_all().unwrap();
        for (a, b) in rec.db.iter().zip(&back.db) {
            assert_close(a, b);
        }
        for (a, b) in rec.queries.iter().zip(&back.queries) {
            assert_close(a, b);
        }
        assert_eq!(back.instance_categories, rec.instance_categories);
        assert_eq!(
            back.db[0].depth.get(3, 0),
            None,
            "invalid depth stays invalid"
        );
        // The index also opens from the HPointLoc_dataset folder itself.
        assert!(DatasetIndex::open(&dir.path().join(layout::DATASET_DIR)).is_ok());
        // No temporary file is left next to the result.
        let names: Vec<_> = std::fs::read_dir(path.parent().unwrap())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 1, "{names:?}");
    }
}

#[test]
fn unknown_scene_lists_the_known_ones() {
    let dir = tempfile::tempdir().unwrap();
    write_point(
        &layout::point_path(dir.path(), "alpha", 0),
        &record(),
        &WriteOptions::default(),
    )
    .unwrap();
    let index = DatasetIndex::open(dir.path()).unwrap();
    let err = index.scene("beta").unwrap_err().to_string();
    assert!(
        err.contains("no scene `beta`") && err.contains("alpha"),
        "{err}"
    );
    let err = DatasetIndex::open(&dir.path().join("nowhere"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("HPointLoc_dataset"), "{err}");
}

/// Write a file field by field, so a test can break exactly one thing.
struct Fields {
    rgb_base: Array4<u8>,
    depth_base: Array4<f32>,
    gps_base: Array2<f32>,
    quat_base: Array2<f32>,
    rgb: Array4<u8>,
    depth: Array4<f32>,
    gps: Array2<f32>,
    quat: Array2<f32>,
}

impl Fields {
    fn good() -> Self {
        let mut quat_base = Array2::zeros((6, 4));
        quat_base.column_mut(0).fill(1.0);
        let mut quat = Array2::zeros((2, 4));
        quat.column_mut(0).fill(1.0);
        Self {
            rgb_base: Array4::zeros((6, 4, 4, 3)),
            depth_base: Array4::from_elem((6, 4, 4, 1), 0.2),
            gps_base: Array2::zeros((6, 3)),
            quat_base,
            rgb: Array4::zeros((2, 4, 4, 3)),
            depth: Array4::from_elem((2, 4, 4, 1), 0.2),
            gps: Array2::zeros((2, 3)),
            quat,
        }
    }

    fn write(&self, path: &Path, skip: &str) {
        let f = hdf5::File::create(path).unwrap();
        macro_rules! put {
            ($name:ident) => {
                if skip != stringify!($name) {
                    f.new_dataset_builder()
                        .with_data(&self.$name)
                        .create(stringify!($name))
                        .unwrap();
                }
            };
        }
        put!(rgb_base);
        put!(depth_base);
        put!(gps_base);
        put!(quat_base);
        put!(rgb);
        put!(depth);
        put!(gps);
        put!(quat);
    }
}

fn open_err(path: &Path) -> String {
    PointReader::open(path).unwrap_err().to_string()
}

fn fixture(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}_point0.hdf5"))
}

#[test]
fn good_handmade_file_opens() {
    let dir = tempfile::tempdir().unwrap();
    let p = fixture(dir.path(), "good");
    Fields::good().write(&p, "");
    let r = PointReader::open(&p).unwrap();
    let v = r.view(Role::Query, 1).unwrap();
    assert_eq!(v.depth.get(0, 0), Some(2.0));
    assert!(v.semantic.is_none());
    let err = r.view(Role::Query, 2).unwrap_err().to_string();
    assert!(err.contains("view 2 requested, the file has 2"), "{err}");
}

#[test]
fn missing_field_is_named() {
    let dir = tempfile::tempdir().unwrap();
    for field in ["rgb_base", "depth_base", "gps", "quat_base", "depth"] {
        let p = fixture(dir.path(), field);
        Fields::good().write(&p, field);
        let err = open_err(&p);
        assert!(err.contains(&format!("field `{field}`: missing")), "{err}");
        assert!(err.contains(p.to_str().unwrap()), "{err}");
    }
}

/// Write `f` as `<name>_point0.hdf5` and check that opening it fails with every part of `want`.
fn refused(dir: &Path, name: &str, f: Fields, want: &[&str]) {
    let p = fixture(dir, name);
    f.write(&p, "");
    let err = open_err(&p);
    assert!(want.iter().all(|w| err.contains(w)), "{err}");
}

#[test]
fn wrong_shape_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut f = Fields::good();
    f.rgb = Array4::zeros((2, 4, 4, 4));
    refused(d, "rgbshape", f, &["field `rgb`", "expected (N, H, W, 3)"]);
    let mut f = Fields::good();
    f.depth_base = Array4::zeros((5, 4, 4, 1));
    refused(
        d,
        "depthcount",
        f,
        &["field `depth_base`", "to match `rgb_base`"],
    );
    let mut f = Fields::good();
    f.gps = Array2::zeros((2, 2));
    refused(d, "gpsshape", f, &["field `gps`", "expected (2, 3)"]);
    // Queries may have another size than the database views (another camera), but each role's
    // depth must match its own colour images.
    let mut f = Fields::good();
    f.rgb = Array4::zeros((2, 5, 4, 3));
    refused(d, "size", f, &["field `depth`", "to match `rgb`"]);
}

#[test]
fn wrong_dtype_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let p = fixture(dir.path(), "dtype");
    let f = hdf5::File::create(&p).unwrap();
    let good = Fields::good();
    // RGB stored as float: HDF5 would convert it silently; the reader must refuse.
    f.new_dataset_builder()
        .with_data(&good.rgb_base.mapv(|v| v as f32))
        .create("rgb_base")
        .unwrap();
    drop(f);
    let err = open_err(&p);
    assert!(
        err.contains("field `rgb_base`") && err.contains("expected uint8"),
        "{err}"
    );

    let p = fixture(dir.path(), "dtype2");
    let f = hdf5::File::create(&p).unwrap();
    f.new_dataset_builder()
        .with_data(&good.rgb_base)
        .create("rgb_base")
        .unwrap();
    f.new_dataset_builder()
        .with_data(&good.depth_base.mapv(|v| (v * 100.0) as u16))
        .create("depth_base")
        .unwrap();
    drop(f);
    let err = open_err(&p);
    assert!(
        err.contains("field `depth_base`") && err.contains("float32 or float64"),
        "{err}"
    );

    let p = fixture(dir.path(), "dtype3");
    let f = hdf5::File::create(&p).unwrap();
    f.new_dataset_builder()
        .with_data(&good.rgb_base)
        .create("rgb_base")
        .unwrap();
    f.new_dataset_builder()
        .with_data(&good.depth_base)
        .create("depth_base")
        .unwrap();
    f.new_dataset_builder()
        .with_data(&Array3::<f32>::zeros((6, 4, 4)))
        .create("semantic_base")
        .unwrap();
    drop(f);
    let err = open_err(&p);
    assert!(
        err.contains("field `semantic_base`") && err.contains("integer"),
        "{err}"
    );
}

#[test]
fn nan_or_zero_pose_is_named_with_its_row() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = Fields::good();
    f.gps_base[[4, 1]] = f32::NAN;
    refused(
        dir.path(),
        "nan",
        f,
        &["gps_base/quat_base", "row 4", "non-finite"],
    );
    let mut f = Fields::good();
    f.quat.fill(0.0);
    refused(dir.path(), "zeroq", f, &["gps/quat", "row 0", "norm"]);
}

#[test]
fn truncated_and_foreign_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = layout::point_path(dir.path(), "s", 0);
    write_point(&p, &record(), &WriteOptions::default()).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    for keep in [bytes.len() / 2, 100, 0] {
        let t = dir.path().join(format!("trunc{keep}_point0.hdf5"));
        std::fs::write(&t, &bytes[..keep]).unwrap();
        let err = open_err(&t);
        assert!(err.contains(t.to_str().unwrap()), "{err}");
    }
    let t = dir.path().join("text_point0.hdf5");
    std::fs::write(&t, b"this is not hdf5").unwrap();
    assert!(open_err(&t).contains("cannot open as HDF5"));
    assert!(open_err(&dir.path().join("absent.hdf5")).contains("no such file"));
}

#[test]
fn writer_refuses_inconsistent_records_and_keeps_the_old_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = layout::point_path(dir.path(), "s", 0);
    write_point(&p, &record(), &WriteOptions::default()).unwrap();
    let before = std::fs::read(&p).unwrap();
    let mut bad = record();
    bad.queries[1].semantic = Some(LabelMap::new(W, H, vec![0; (W * H) as usize]).unwrap());
    let err = write_point(&p, &bad, &WriteOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("semantic") && err.contains("all or none"),
        "{err}"
    );
    assert_eq!(
        std::fs::read(&p).unwrap(),
        before,
        "a failed write must not touch the existing file"
    );
    let names: Vec<_> = std::fs::read_dir(p.parent().unwrap())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names.len(), 1, "no temporary left behind: {names:?}");
    let err = write_point(&p, &PointRecord::default(), &WriteOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("at least one view"), "{err}");
}
