//! pntr's HDF5 files and h5py's agree both ways: pntr reads what h5py writes in the real dataset's
//! layout, and h5py (used the way the HPointLoc code uses it) reads what pntr writes.

use pntr_core::pose_to_hpointloc;
use pntr_dataset::{layout, DatasetIndex, PointReader, Role};
use pntr_synth::SynthConfig;
use pntr_tests::run_python;

#[test]
fn reads_a_file_written_by_h5py() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ref_point3.hdf5");
    run_python("h5py_interop.py", &["write".as_ref(), path.as_os_str()]);
    let r = PointReader::open(&path).unwrap();
    assert_eq!((r.width(), r.height()), (7, 5));
    assert_eq!((r.count(Role::Database), r.count(Role::Query)), (6, 3));
    for (role, n, rgb_base, depth_base) in [
        (Role::Database, 6, 0u32, 0.0f32),
        (Role::Query, 3, 100, 0.2),
    ] {
        for i in 0..n {
            let v = r.view(role, i).unwrap();
            for y in 0..5u32 {
                for x in 0..7u32 {
                    let px = v.rgb.pixel(x, y);
                    for c in 0..3u32 {
                        let want = (i as u32 * 31 + y * 7 + x * 3 + c + rgb_base) % 256;
                        assert_eq!(px[c as usize] as u32, want);
                    }
                    let want =
                        0.05 * (i as f32 + 1.0) + 0.01 * y as f32 + 0.001 * x as f32 + depth_base;
                    match v.depth.get(x, y) {
                        None => assert_eq!((x, y), (0, 0), "only pixel (0,0) is invalid"),
                        Some(d) => {
                            assert!((d - want * 10.0).abs() < 1e-4, "{d} vs {}", want * 10.0)
                        }
                    }
                }
            }
            let base = if role == Role::Database { 0.0 } else { 1.0 };
            let t = v.world_from_camera.translation.vector;
            assert!((t.x - (i as f64 + base)).abs() < 1e-5 && (t.y - 1.25).abs() < 1e-6);
            let yaw = 0.3 * i as f64 + base;
            let q = nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::y_axis(), yaw);
            assert!(v.world_from_camera.rotation.angle_to(&q) < 1e-5);
            assert_eq!(v.semantic.is_some(), role == Role::Database);
        }
    }
    let sem = r.view(Role::Database, 1).unwrap().semantic.unwrap();
    assert_eq!(sem.get(0, 0), (35 % 11) as u32);
}

#[test]
fn h5py_reads_a_synthesized_file_like_the_real_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = SynthConfig {
        points_per_scene: 1,
        queries_per_point: 4,
        seed: 3,
        ..SynthConfig::default()
    };
    let planned = pntr_synth::plan_all(&cfg);
    pntr_synth::synthesize(&cfg, dir.path(), planned, &|| {}).unwrap();
    let index = DatasetIndex::open(dir.path()).unwrap();
    let entry = &index.scenes[0].points[0];
    assert_eq!(entry.path, layout::point_path(dir.path(), "synth000", 0));
    let out = run_python(
        "h5py_interop.py",
        &["check".as_ref(), entry.path.as_os_str()],
    );
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let r = entry.open().unwrap();
    let nq = r.count(Role::Query);
    assert!(nq > 0);
    let fields = &v["fields"];
    let expect = [
        ("rgb_base", serde_json::json!([6, 256, 256, 3]), "uint8"),
        ("depth_base", serde_json::json!([6, 256, 256, 1]), "float32"),
        ("semantic_base", serde_json::json!([6, 256, 256]), "uint32"),
        ("gps_base", serde_json::json!([6, 3]), "float32"),
        ("quat_base", serde_json::json!([6, 4]), "float32"),
        ("rgb", serde_json::json!([nq, 256, 256, 3]), "uint8"),
        ("depth", serde_json::json!([nq, 256, 256, 1]), "float32"),
        ("gps", serde_json::json!([nq, 3]), "float32"),
        ("quat", serde_json::json!([nq, 4]), "float32"),
    ];
    for (name, shape, dtype) in expect {
        assert_eq!(fields[name]["shape"], shape, "{name}");
        assert_eq!(fields[name]["dtype"], dtype, "{name}");
    }
    for role in [Role::Database, Role::Query] {
        let suffix = if role == Role::Database { "_base" } else { "" };
        let (mut rgb, mut depth, mut gps) = (0i64, 0f64, [0f64; 3]);
        for i in 0..r.count(role) {
            let view = r.view(role, i).unwrap();
            rgb += view.rgb.data.iter().map(|&b| b as i64).sum::<i64>();
            // h5py sums the stored values, where our invalid (far-clip) pixels read as 10 m.
            depth += view
                .depth
                .to_hpointloc()
                .iter()
                .map(|&d| d as f64 * 10.0)
                .sum::<f64>();
            let (g, _) = pose_to_hpointloc(&view.world_from_camera);
            for k in 0..3 {
                gps[k] += g[k] as f32 as f64;
            }
        }
        assert_eq!(v["sums"][format!("rgb{suffix}")].as_i64().unwrap(), rgb);
        let hd = v["sums"][format!("depth_m{suffix}")].as_f64().unwrap();
        assert!(
            (hd - depth).abs() <= 1e-6 * depth.abs().max(1.0),
            "{hd} vs {depth}"
        );
        for k in 0..3 {
            let hg = v["sums"][format!("gps{suffix}")][k].as_f64().unwrap();
            assert!((hg - gps[k]).abs() < 1e-4, "{hg} vs {}", gps[k]);
        }
        let (_, q) = pose_to_hpointloc(&r.view(role, 0).unwrap().world_from_camera);
        for k in 0..4 {
            let hq = v["sums"][format!("quat0{suffix}")][k].as_f64().unwrap();
            assert!((hq - q[k]).abs() < 1e-6, "quat[{k}] {hq} vs {}", q[k]);
        }
    }
}
