//! Camera poses, the two camera-axis conventions, and conversion to and from HPointLoc's fields.

use nalgebra::{Isometry3, Matrix3, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Which way a camera's own axes point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum CameraAxes {
    /// Habitat / OpenGL: x right, y up, the camera looks along -z. HPointLoc's `quat` uses this.
    Habitat,
    /// OpenCV: x right, y down, the camera looks along +z. Pixel back-projection uses this.
    OpenCv,
}

impl CameraAxes {
    /// The name maps and files use: `habitat` or `opencv`.
    pub fn name(self) -> &'static str {
        match self {
            CameraAxes::Habitat => "habitat",
            CameraAxes::OpenCv => "opencv",
        }
    }

    /// The convention a name gives (`habitat`, or `opencv` / `optical`, case-insensitive); `None`
    /// for anything else.
    pub fn parse(name: &str) -> Option<Self> {
        match name.to_ascii_lowercase().as_str() {
            "habitat" => Some(CameraAxes::Habitat),
            "opencv" | "optical" => Some(CameraAxes::OpenCv),
            _ => None,
        }
    }
}

/// Errors when a pose read from outside is not a rigid transform.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PoseError {
    /// A component is NaN or infinite.
    #[error("pose has a non-finite component: {0}")]
    NonFinite(String),
    /// The quaternion is too far from unit length to be a rotation (norm given).
    #[error("quaternion norm {0} is not close to 1 (expected a unit quaternion w,x,y,z)")]
    NotUnit(f64),
}

/// The rotation that turns one camera-axis convention into the other. Both conventions share x; y and
/// z are negated, so the matrix is its own inverse.
fn flip_yz() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0)))
}

/// Re-express `world_from_camera` for a camera whose axes follow `to` instead of `from`.
///
/// The camera centre does not move; only the rotation's columns 1 and 2 are negated.
pub fn convert_axes(
    world_from_camera: &Isometry3<f64>,
    from: CameraAxes,
    to: CameraAxes,
) -> Isometry3<f64> {
    if from == to {
        return *world_from_camera;
    }
    let flip = UnitQuaternion::from_rotation_matrix(&flip_yz());
    Isometry3::from_parts(
        world_from_camera.translation,
        world_from_camera.rotation * flip,
    )
}

/// Build `world_from_camera` (Habitat axes) from HPointLoc's `gps` (tx, ty, tz) and `quat` (w, x, y, z).
///
/// The quaternion is normalised; one whose norm is outside 0.9..1.1 or that has a non-finite component
/// is refused, because it is a corrupt record rather than rounding.
pub fn pose_from_hpointloc(
    gps: [f64; 3],
    quat_wxyz: [f64; 4],
) -> Result<Isometry3<f64>, PoseError> {
    if gps.iter().chain(quat_wxyz.iter()).any(|v| !v.is_finite()) {
        return Err(PoseError::NonFinite(format!(
            "gps={gps:?} quat(w,x,y,z)={quat_wxyz:?}"
        )));
    }
    let q = Quaternion::new(quat_wxyz[0], quat_wxyz[1], quat_wxyz[2], quat_wxyz[3]);
    let norm = q.norm();
    if !(0.9..=1.1).contains(&norm) {
        return Err(PoseError::NotUnit(norm));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(gps[0], gps[1], gps[2]),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// The inverse of [`pose_from_hpointloc`]: `(gps, quat_wxyz)` of a Habitat-axes `world_from_camera`.
/// The quaternion is returned with w >= 0.
pub fn pose_to_hpointloc(world_from_camera: &Isometry3<f64>) -> ([f64; 3], [f64; 4]) {
    let t = world_from_camera.translation.vector;
    ([t.x, t.y, t.z], canonical_wxyz(&world_from_camera.rotation))
}

/// A world frame's up axis, as maps record it (`y` for HPointLoc and `pntr synth`, `z` for REP 103
/// frames such as a ROS `map`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpAxis {
    /// +y is up (HPointLoc, Habitat, `pntr synth`).
    Y,
    /// +z is up (REP 103).
    Z,
}

impl UpAxis {
    /// `z` (any case) is [`UpAxis::Z`]; anything else, as maps read it, [`UpAxis::Y`].
    pub fn parse(name: &str) -> Self {
        if name.eq_ignore_ascii_case("z") {
            UpAxis::Z
        } else {
            UpAxis::Y
        }
    }
}

/// `ros_world_from_map_world`: the rotation taking points of a map's world frame into the REP 103
/// (z-up) frame that ROS answers use. Identity for a z-up map; for a y-up map a rotation of +90
/// degrees about x, `(x, y, z) -> (x, -z, y)`, which keeps x and puts the map's up (+y) on +z.
pub fn ros_from_map_world(up: UpAxis) -> UnitQuaternion<f64> {
    match up {
        UpAxis::Z => UnitQuaternion::identity(),
        UpAxis::Y => {
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2)
        }
    }
}

/// A map-convention `world_from_camera` (the map's world frame and camera axes `axes`) as ROS
/// expects it: `ros_map_from_camera_optical` (z-up world, optical camera axes x right, y down, z
/// forward). The inverse is [`ros_to_map`].
pub fn map_to_ros(
    world_from_camera: &Isometry3<f64>,
    up: UpAxis,
    axes: CameraAxes,
) -> Isometry3<f64> {
    let optical = convert_axes(world_from_camera, axes, CameraAxes::OpenCv);
    Isometry3::from_parts(Translation3::identity(), ros_from_map_world(up)) * optical
}

/// The inverse of [`map_to_ros`]: a ROS-convention pose back in the map's frame and camera axes.
pub fn ros_to_map(
    ros_from_camera: &Isometry3<f64>,
    up: UpAxis,
    axes: CameraAxes,
) -> Isometry3<f64> {
    let world = Isometry3::from_parts(Translation3::identity(), ros_from_map_world(up).inverse())
        * ros_from_camera;
    convert_axes(&world, CameraAxes::OpenCv, axes)
}

/// A 6x6 pose covariance (row-major, 36 values, ROS order: x, y, z, rotation about x, y, z, all in
/// the world frame) re-expressed after the world frame is rotated by `rotation`: `J C J^T` with
/// `J = diag(R, R)`. The camera axes do not enter (the rotation part is about the world's axes).
/// Returns `None` unless `covariance` has 36 values.
pub fn rotate_covariance(covariance: &[f64], rotation: &UnitQuaternion<f64>) -> Option<Vec<f64>> {
    if covariance.len() != 36 {
        return None;
    }
    let c = nalgebra::Matrix6::from_row_slice(covariance);
    let r = rotation.to_rotation_matrix().into_inner();
    let mut j = nalgebra::Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    let out = j * c * j.transpose();
    Some(
        (0..6)
            .flat_map(|i| (0..6).map(move |k| (i, k)))
            .map(|(i, k)| out[(i, k)])
            .collect(),
    )
}

/// The same rotation with w >= 0 (`q` and `-q` are one rotation; every pntr output uses this sign).
pub fn canonical_wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    let q = q.quaternion();
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.w, s * q.i, s * q.j, s * q.k]
}

/// Geodesic angle between two rotations, in degrees: the angle of `a^T b`, in 0..=180.
pub fn rotation_angle_deg(a: &UnitQuaternion<f64>, b: &UnitQuaternion<f64>) -> f64 {
    a.angle_to(b).to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn habitat_camera_looks_along_minus_z_and_opencv_along_plus_z() {
        // A Habitat camera with yaw 90 degrees about world y looks along world -x.
        let wfc = Isometry3::from_parts(
            Translation3::new(1.0, 1.25, 2.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2),
        );
        let forward_habitat = wfc.rotation * Vector3::new(0.0, 0.0, -1.0);
        assert!((forward_habitat - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
        let cv = convert_axes(&wfc, CameraAxes::Habitat, CameraAxes::OpenCv);
        let forward_cv = cv.rotation * Vector3::new(0.0, 0.0, 1.0);
        assert!((forward_cv - forward_habitat).norm() < 1e-12);
        // Image "down" in OpenCV is world -y for an upright camera.
        assert!((cv.rotation * Vector3::y() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
        assert_eq!(cv.translation, wfc.translation);
        let back = convert_axes(&cv, CameraAxes::OpenCv, CameraAxes::Habitat);
        assert!(rotation_angle_deg(&back.rotation, &wfc.rotation) < 1e-9);
    }

    #[test]
    fn hpointloc_round_trip_and_refusals() {
        let wfc = pose_from_hpointloc([1.0, 2.0, 3.0], [0.5, 0.5, -0.5, 0.5]).unwrap();
        let (g, q) = pose_to_hpointloc(&wfc);
        assert_eq!(g, [1.0, 2.0, 3.0]);
        for (a, b) in q.iter().zip([0.5, 0.5, -0.5, 0.5]) {
            assert!((a - b).abs() < 1e-12);
        }
        assert!(matches!(
            pose_from_hpointloc([f64::NAN, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]),
            Err(PoseError::NonFinite(_))
        ));
        assert!(matches!(
            pose_from_hpointloc([0.0; 3], [0.0; 4]),
            Err(PoseError::NotUnit(_))
        ));
    }

    #[test]
    fn geodesic_angle_is_not_folded() {
        let a = UnitQuaternion::identity();
        let b = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI);
        assert!((rotation_angle_deg(&a, &b) - 180.0).abs() < 1e-9);
        let c = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.3);
        assert!((rotation_angle_deg(&a, &c) - 0.3f64.to_degrees()).abs() < 1e-9);
    }

    #[test]
    fn ros_convention_puts_up_on_z_and_looks_along_optical_z() {
        // An upright Habitat camera in a y-up map, looking along world -x (yaw 90 degrees about y).
        let wfc = Isometry3::from_parts(
            Translation3::new(1.0, 1.25, 2.0),
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2),
        );
        let ros = map_to_ros(&wfc, UpAxis::Y, CameraAxes::Habitat);
        // Position (x, y, z) -> (x, -z, y): the camera height 1.25 becomes z.
        assert!((ros.translation.vector - Vector3::new(1.0, -2.0, 1.25)).norm() < 1e-12);
        // Optical z (forward) is still world -x, which Rx(90) leaves as -x.
        let forward = ros.rotation * Vector3::z();
        assert!((forward - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
        // Optical y (image down) points along ROS -z.
        assert!((ros.rotation * Vector3::y() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        let back = ros_to_map(&ros, UpAxis::Y, CameraAxes::Habitat);
        assert!((back.translation.vector - wfc.translation.vector).norm() < 1e-12);
        assert!(rotation_angle_deg(&back.rotation, &wfc.rotation) < 1e-9);
        // A z-up optical map is already in ROS conventions.
        let same = map_to_ros(&wfc, UpAxis::Z, CameraAxes::OpenCv);
        assert_eq!(same, wfc);
    }

    #[test]
    fn covariance_rotates_with_the_world_and_w_is_non_negative() {
        // Variance 4 along the map's y (up) and 9 in rotation about y become z's under ROS.
        let mut c = vec![0.0; 36];
        c[0] = 1.0;
        c[7] = 4.0;
        c[14] = 0.25;
        c[21] = 0.01;
        c[28] = 0.09;
        c[35] = 0.04;
        let r = rotate_covariance(&c, &ros_from_map_world(UpAxis::Y)).unwrap();
        let diag: Vec<f64> = (0..6).map(|i| r[i * 7]).collect();
        for (a, b) in diag.iter().zip([1.0, 0.25, 4.0, 0.01, 0.04, 0.09]) {
            assert!((a - b).abs() < 1e-12, "{diag:?}");
        }
        assert!(rotate_covariance(&c[..35], &UnitQuaternion::identity()).is_none());
        let q = UnitQuaternion::from_quaternion(Quaternion::new(-0.5, 0.5, 0.5, 0.5));
        let w = canonical_wxyz(&q);
        assert!(w[0] >= 0.0 && (w[1] + 0.5).abs() < 1e-12);
    }
}
