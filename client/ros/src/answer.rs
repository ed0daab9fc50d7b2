//! From the server's answer (the camera's optical frame in the map, ROS conventions) to what a
//! ROS graph consumes: the base frame's pose with its covariance carried across the camera's lever
//! arm, and `map -> odom` as AMCL publishes it.

use nalgebra::{Isometry3, Matrix3, Matrix6, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::proto;

/// The pose of a LOCALIZED answer (map_from_camera_optical with FRAME_CONVENTION_ROS).
pub fn pose_of(r: &proto::LocalizeResponse) -> Option<Isometry3<f64>> {
    let p = r.pose.as_ref()?;
    let (t, q) = (p.translation.as_ref()?, p.rotation.as_ref()?);
    let pose = Isometry3::from_parts(
        Translation3::new(t.x, t.y, t.z),
        UnitQuaternion::from_quaternion(Quaternion::new(q.w, q.x, q.y, q.z)),
    );
    (pose.translation.vector.iter().all(|v| v.is_finite())
        && pose.rotation.coords.iter().all(|v| v.is_finite()))
    .then_some(pose)
}

/// The skew-symmetric matrix of `v` (`skew(v) * w = v x w`).
fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The base frame's pose and covariance from the camera's.
///
/// `map_from_camera`: the answer; `covariance_camera`: its 6x6 covariance (row-major, x y z and
/// rotations about the map's x y z axes, metres² and radians²); `base_from_camera`: the camera's
/// mounting (from TF). The base lies at `p_b = p_c + R_c t`, with `t` the base's origin in the camera
/// frame; a rotation error `dθ` (about the map's axes) moves it by `dθ x l`, `l = p_b - p_c` the lever
/// arm in the map, so the covariance is `J Σ Jᵀ` with `J = [[I, -[l]x], [0, I]]` (the rotation block is
/// unchanged: both frames turn together). Returns (map_from_base, covariance of the base, the same
/// order and units).
pub fn base_pose(
    map_from_camera: &Isometry3<f64>,
    covariance_camera: &[f64],
    base_from_camera: &Isometry3<f64>,
) -> (Isometry3<f64>, [f64; 36]) {
    let map_from_base = map_from_camera * base_from_camera.inverse();
    let lever = map_from_base.translation.vector - map_from_camera.translation.vector;
    let mut jacobian = Matrix6::identity();
    jacobian
        .fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-skew(&lever)));
    let sigma = if covariance_camera.len() == 36 {
        Matrix6::from_row_slice(covariance_camera)
    } else {
        Matrix6::zeros()
    };
    let carried = jacobian * sigma * jacobian.transpose();
    let carried = (carried + carried.transpose()) * 0.5;
    let mut out = [0.0; 36];
    for r in 0..6 {
        for c in 0..6 {
            out[r * 6 + c] = carried[(r, c)];
        }
    }
    (map_from_base, out)
}

/// `map -> odom`: the transform that puts odometry's base pose (`odom_from_base`, at the image's
/// stamp) onto the localized one.
pub fn map_from_odom(
    map_from_base: &Isometry3<f64>,
    odom_from_base: &Isometry3<f64>,
) -> Isometry3<f64> {
    map_from_base * odom_from_base.inverse()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lever_arm_turns_rotation_variance_into_position_variance() {
        // Camera 0.5 m ahead of the base (along the base's x); optical axes turned as REP 103.
        let optical = UnitQuaternion::from_euler_angles(
            -std::f64::consts::FRAC_PI_2,
            0.0,
            -std::f64::consts::FRAC_PI_2,
        );
        let base_from_camera = Isometry3::from_parts(Translation3::new(0.5, 0.0, 0.0), optical);
        let map_from_base =
            Isometry3::new(Vector3::new(2.0, 1.0, 0.0), Vector3::new(0.0, 0.0, 0.3));
        let map_from_camera = map_from_base * base_from_camera;
        // Only yaw uncertain: 0.01 rad².
        let mut cov = [0.0; 36];
        cov[35] = 0.01;
        let (base, c) = base_pose(&map_from_camera, &cov, &base_from_camera);
        assert!((base.translation.vector - map_from_base.translation.vector).norm() < 1e-12);
        assert!(base.rotation.angle_to(&map_from_base.rotation) < 1e-12);
        // A yaw error of the camera swings the base on a 0.5 m arm: position variance 0.25 * 0.01
        // across the arm, none along it, and the yaw variance unchanged.
        let arm =
            (map_from_base.translation.vector - map_from_camera.translation.vector).normalize();
        let p = Matrix3::from_fn(|r, col| c[r * 6 + col]);
        let across = Vector3::new(-arm.y, arm.x, 0.0);
        assert!((across.dot(&(p * across)) - 0.0025).abs() < 1e-12);
        assert!(arm.dot(&(p * arm)).abs() < 1e-12);
        assert!((c[35] - 0.01).abs() < 1e-15);
        for r in 0..6 {
            for col in 0..6 {
                assert!((c[r * 6 + col] - c[col * 6 + r]).abs() < 1e-15);
            }
        }
        // map -> odom puts odometry's pose onto the answer.
        let odom_from_base =
            Isometry3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.1));
        let m = map_from_odom(&base, &odom_from_base);
        assert!(((m * odom_from_base).translation.vector - base.translation.vector).norm() < 1e-12);
    }
}
