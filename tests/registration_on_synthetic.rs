//! Registration on rendered depth: the solvers work on the geometry the pipeline will feed them.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use pntr_core::{convert_axes, CameraAxes, DepthMap, Intrinsics};
use pntr_registration::icp::{icp_clouds, IcpParams};
use pntr_registration::teaser::{solve, TeaserParams};
use pntr_registration::Rigid;
use pntr_synth::{plan_scene, Renderer, SynthConfig};

/// Back-project every `step`-th pixel with valid depth into the OpenCV camera frame.
fn cloud(depth: &DepthMap, k: &Intrinsics, step: u32) -> Vec<Vector3<f64>> {
    let mut out = Vec::new();
    for row in (0..k.height).step_by(step as usize) {
        for col in (0..k.width).step_by(step as usize) {
            if let Some(z) = depth.get(col, row) {
                out.push(k.backproject(col as f64, row as f64, z as f64).coords);
            }
        }
    }
    out
}

fn setup() -> (
    Renderer<'static>,
    Isometry3<f64>,
    Isometry3<f64>,
    Intrinsics,
) {
    let planned = Box::leak(Box::new(plan_scene(
        &SynthConfig {
            points_per_scene: 2,
            queries_per_point: 1,
            seed: 12,
            ..Default::default()
        },
        0,
    )));
    let renderer = Renderer::new(&planned.scene);
    let a = planned.points[0].db[0];
    // The same place seen after turning 10 degrees and moving about 0.3 m.
    let b = Isometry3::from_parts(
        Translation3::from(a.translation.vector + Vector3::new(0.2, 0.0, 0.22)),
        a.rotation * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 10f64.to_radians()),
    );
    (renderer, a, b, Intrinsics::hpointloc())
}

fn cv(p: &Isometry3<f64>) -> Isometry3<f64> {
    convert_axes(p, CameraAxes::Habitat, CameraAxes::OpenCv)
}

#[test]
fn icp_aligns_two_rendered_depth_clouds() {
    let (renderer, a, b, k) = setup();
    let fa = renderer.render(&a, &k, 1);
    let fb = renderer.render(&b, &k, 2);
    let ca = cloud(&fa.depth, &k, 3);
    let cb = cloud(&fb.depth, &k, 3);
    // Truth: a_from_b = (world_from_a)^-1 * world_from_b, in OpenCV axes.
    let truth = Rigid::from_isometry(&(cv(&a).inverse() * cv(&b)));
    let r = icp_clouds(&cb, &ca, Rigid::identity(), &IcpParams::default());
    assert!(r.valid, "{r:?}");
    let rot = r.transform.rotation.angle_to(&truth.rotation).to_degrees();
    let trans = (r.transform.translation - truth.translation).norm();
    assert!(
        rot < 1.0 && trans < 0.05,
        "rotation {rot} deg, translation {trans} m"
    );
}

#[test]
fn teaser_registers_keypoint_like_correspondences_between_views() {
    let (renderer, a, b, k) = setup();
    let fa = renderer.render(&a, &k, 1);
    let fb = renderer.render(&b, &k, 2);
    let a_from_b = cv(&a).inverse() * cv(&b);
    // Pixels of view b, their 3D points in b and, where visible, the same surface point in a
    // (found through a's depth, as matched keypoints would be); every third pair is scrambled.
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for row in (4..k.height - 4).step_by(9) {
        for col in (4..k.width - 4).step_by(9) {
            let Some(zb) = fb.depth.get(col, row) else {
                continue;
            };
            let pb = k.backproject(col as f64, row as f64, zb as f64);
            let pa = a_from_b * pb;
            let Some(uv) = k.project(&pa) else { continue };
            let Some((c, r)) = k.pixel_of(&uv) else {
                continue;
            };
            let Some(za) = fa.depth.get(c, r) else {
                continue;
            };
            if (za as f64 - pa.z).abs() > 0.05 {
                continue; // occluded in a
            }
            src.push(pb.coords);
            dst.push(k.backproject(c as f64, r as f64, za as f64).coords);
        }
    }
    assert!(src.len() > 200, "{} co-visible samples", src.len());
    // Replace a third of the destinations with those of random other samples (a seeded shuffle:
    // real mismatches are unstructured; an index shift on this regular grid would instead create a
    // translated copy of the scene, which is itself rigidly consistent).
    let n = dst.len();
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let originals = dst.clone();
    for i in (0..n).step_by(3) {
        dst[i] = originals[(next() % n as u64) as usize];
    }
    let res = solve(&src, &dst, &TeaserParams::default());
    assert!(res.valid, "{:?}", res.reason);
    let rot = res
        .transform
        .rotation
        .angle_to(&a_from_b.rotation.to_rotation_matrix())
        .to_degrees();
    let trans = (res.transform.translation - a_from_b.translation.vector).norm();
    assert!(
        rot < 1.0 && trans < 0.03,
        "rotation {rot} deg, translation {trans} m"
    );
}
