//! Client-side helpers: build `LocalizeRequest`s from pntr's image types and read poses back.
//!
//! They live beside the server so that every client (the tests, `pntr eval --remote`, tools) encodes
//! frames exactly as the server decodes them, from one definition.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use pntr_core::pose::{
    canonical_wxyz, map_to_ros, ros_from_map_world, ros_to_map, rotate_covariance, UpAxis,
};
use pntr_core::{CameraAxes, DepthMap, Intrinsics, RgbImage};
use pntr_pipeline::pipeline::Cause;
use pntr_pipeline::prior::{Mode, Region};

use crate::proto;

/// The wire form of a prior region: its centre as the pose's translation (identity rotation) and its
/// radius.
pub fn prior_message(r: &Region) -> proto::Prior {
    proto::Prior {
        pose: Some(proto::Pose {
            translation: Some(proto::Vector3 {
                x: r.center_m.x,
                y: r.center_m.y,
                z: r.center_m.z,
            }),
            rotation: Some(proto::Quaternion {
                w: 1.0,
                x: 0.0,
                y: 0.0,
                z: 0.0,
            }),
        }),
        covariance: Vec::new(),
        radius_m: r.radius_m,
    }
}

/// The wire form of the path that answered.
pub fn mode_message(m: Mode) -> proto::Mode {
    match m {
        Mode::Global => proto::Mode::Global,
        Mode::Prior => proto::Mode::Prior,
        Mode::Tracking => proto::Mode::Tracking,
    }
}

/// The wire form of why a frame is NOT_LOCALIZED (`None`: LOCALIZED, UNSPECIFIED).
pub fn cause_message(c: Option<Cause>) -> proto::NotLocalizedCause {
    match c {
        None => proto::NotLocalizedCause::Unspecified,
        Some(Cause::NoMatch) => proto::NotLocalizedCause::NoMatch,
        Some(Cause::Unverified) => proto::NotLocalizedCause::Unverified,
        Some(Cause::LookAlike) => proto::NotLocalizedCause::LookAlike,
        Some(Cause::OutsideMap) => proto::NotLocalizedCause::OutsideMap,
        Some(Cause::BadInput) => proto::NotLocalizedCause::BadInput,
    }
}

/// The `cause` label of a NOT_LOCALIZED answer's wire `cause` ([`Cause::name`], which is the proto
/// value's name); an unset one (a NOT_LOCALIZED answer made before its cause was known) counts as
/// `NO_MATCH`.
pub fn cause_name(wire: i32) -> &'static str {
    match cause_label(wire) {
        "" => Cause::NoMatch.name(),
        name => name,
    }
}

/// How clients show a wire `cause`: its name (`NO_MATCH`, ..., `OUTSIDE_MAP`), or "" when unset
/// (LOCALIZED) or unknown to this build.
pub fn cause_label(wire: i32) -> &'static str {
    match proto::NotLocalizedCause::try_from(wire) {
        Ok(proto::NotLocalizedCause::Unspecified) | Err(_) => "",
        Ok(c) => c.as_str_name(),
    }
}

/// A stream answer's [`proto::TrackState`] without its prefix (`ESTABLISHED`, `CARRIED`, ...);
/// empty for unary answers, which have no track.
pub fn track_state_label(wire: i32) -> &'static str {
    match proto::TrackState::try_from(wire) {
        Ok(proto::TrackState::Unspecified) | Err(_) => "",
        Ok(proto::TrackState::None) => "NONE",
        Ok(proto::TrackState::ReAcquiring) => "RE_ACQUIRING",
        Ok(proto::TrackState::Established) => "ESTABLISHED",
        Ok(proto::TrackState::Carried) => "CARRIED",
    }
}

/// The wire form of a camera (distortion sent only when there is some).
pub fn intrinsics_message(k: &Intrinsics) -> proto::Intrinsics {
    proto::Intrinsics {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        distortion: if k.is_distorted() {
            k.distortion.to_vec()
        } else {
            Vec::new()
        },
    }
}

/// A request with RAW_RGB8 colour and FLOAT32_METERS depth (missing depth sent as 0).
pub fn raw_request(
    rgb: &RgbImage,
    depth: &DepthMap,
    k: Option<&Intrinsics>,
) -> proto::LocalizeRequest {
    proto::LocalizeRequest {
        rgb: Some(proto::Image {
            width: rgb.width,
            height: rgb.height,
            encoding: proto::ImageEncoding::RawRgb8 as i32,
            data: rgb.data.clone(),
        }),
        depth: Some(proto::Depth {
            width: depth.width,
            height: depth.height,
            encoding: proto::DepthEncoding::Float32Meters as i32,
            data: depth.data.iter().flat_map(|d| d.to_le_bytes()).collect(),
        }),
        intrinsics: k.map(intrinsics_message),
        ..Default::default()
    }
}

/// A request with PNG colour and PNG16_MILLIMETERS depth (depth rounded to whole millimetres and
/// clamped to 65.535 m).
pub fn png_request(
    rgb: &RgbImage,
    depth: &DepthMap,
    k: Option<&Intrinsics>,
) -> Result<proto::LocalizeRequest, png::EncodingError> {
    let mm: Vec<u8> = depth
        .to_millimetres()
        .into_iter()
        .flat_map(u16::to_be_bytes)
        .collect();
    Ok(proto::LocalizeRequest {
        rgb: Some(proto::Image {
            width: rgb.width,
            height: rgb.height,
            encoding: proto::ImageEncoding::Png as i32,
            data: encode_png(
                rgb.width,
                rgb.height,
                png::ColorType::Rgb,
                png::BitDepth::Eight,
                &rgb.data,
            )?,
        }),
        depth: Some(proto::Depth {
            width: depth.width,
            height: depth.height,
            encoding: proto::DepthEncoding::Png16Millimeters as i32,
            data: encode_png(
                depth.width,
                depth.height,
                png::ColorType::Grayscale,
                png::BitDepth::Sixteen,
                &mm,
            )?,
        }),
        intrinsics: k.map(intrinsics_message),
        ..Default::default()
    })
}

/// Encode a PNG (16-bit samples big-endian, as PNG stores them).
pub fn encode_png(
    width: u32,
    height: u32,
    color: png::ColorType,
    depth: png::BitDepth,
    data: &[u8],
) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(color);
        enc.set_depth(depth);
        let mut w = enc.write_header()?;
        w.write_image_data(data)?;
        w.finish()?;
    }
    Ok(out)
}

/// The pose of a response as `world_from_camera`, or `None` when it has none.
pub fn pose(p: Option<&proto::Pose>) -> Option<Isometry3<f64>> {
    let p = p?;
    let (t, r) = (p.translation.as_ref()?, p.rotation.as_ref()?);
    Some(Isometry3::from_parts(
        Translation3::new(t.x, t.y, t.z),
        UnitQuaternion::from_quaternion(Quaternion::new(r.w, r.x, r.y, r.z)),
    ))
}

/// The wire form of a pose (its quaternion with w >= 0).
pub fn to_proto_pose(p: &Isometry3<f64>) -> proto::Pose {
    let t = p.translation.vector;
    let [w, x, y, z] = canonical_wxyz(&p.rotation);
    proto::Pose {
        translation: Some(proto::Vector3 {
            x: t.x,
            y: t.y,
            z: t.z,
        }),
        rotation: Some(proto::Quaternion { w, x, y, z }),
    }
}

/// The axes a map's poses are in: its world's up axis and its camera axes (from its header).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapFrames {
    /// The world's up axis.
    pub up: UpAxis,
    /// The camera axes of the map's poses.
    pub camera: CameraAxes,
}

impl Default for MapFrames {
    /// HPointLoc's: y up, Habitat camera axes.
    fn default() -> Self {
        Self {
            up: UpAxis::Y,
            camera: CameraAxes::Habitat,
        }
    }
}

impl MapFrames {
    /// The frames of a map header's `up_axis` and `camera_axes`.
    pub fn of(header: &pntr_pipeline::map::MapHeader) -> Self {
        Self {
            up: UpAxis::parse(&header.up_axis),
            camera: header.axes(),
        }
    }

    /// The frames a server reports in `GetMapInfo` (y up and Habitat's axes for what it leaves
    /// empty or does not know).
    pub fn of_info(info: &proto::MapInfo) -> Self {
        Self {
            up: UpAxis::parse(&info.up_axis),
            camera: CameraAxes::parse(&info.camera_axes).unwrap_or(CameraAxes::Habitat),
        }
    }

    /// A `world_from_camera` in these frames as ROS expects it ([`pntr_core::pose::map_to_ros`]).
    pub fn pose_to_ros(&self, world_from_camera: &Isometry3<f64>) -> Isometry3<f64> {
        map_to_ros(world_from_camera, self.up, self.camera)
    }

    /// A 36-value covariance in the map's world frame rotated into the ROS frame; empty for
    /// anything but 36 values ([`pntr_core::pose::rotate_covariance`]).
    pub fn covariance_to_ros(&self, covariance: &[f64]) -> Vec<f64> {
        rotate_covariance(covariance, &ros_from_map_world(self.up)).unwrap_or_default()
    }

    /// `ros_world_from_map_world` as a wire pose (rotation only).
    pub fn ros_from_map(&self) -> proto::Pose {
        to_proto_pose(&Isometry3::from_parts(
            Translation3::identity(),
            ros_from_map_world(self.up),
        ))
    }
}

/// `map` or `ros` for a FrameConvention value (as answers and MapInfo carry it); `unspecified`
/// otherwise.
pub fn convention_name(value: i32) -> &'static str {
    match proto::FrameConvention::try_from(value) {
        Ok(proto::FrameConvention::Map) => "map",
        Ok(proto::FrameConvention::Ros) => "ros",
        _ => "unspecified",
    }
}

/// Re-express an answer given in the map's own convention in `convention`: under ROS the pose
/// becomes `ros_map_from_camera_optical` and the covariance is rotated into the ROS map frame
/// ([`pntr_core::pose::map_to_ros`], [`pntr_core::pose::rotate_covariance`]). Sets
/// `frame_convention`. `convention` must not be UNSPECIFIED (it is then treated as MAP).
pub fn answer_in(
    r: &mut proto::LocalizeResponse,
    convention: proto::FrameConvention,
    frames: MapFrames,
) {
    if convention == proto::FrameConvention::Ros {
        if let Some(p) = pose(r.pose.as_ref()) {
            r.pose = Some(to_proto_pose(&frames.pose_to_ros(&p)));
        }
        r.covariance = frames.covariance_to_ros(&r.covariance);
        r.frame_convention = proto::FrameConvention::Ros as i32;
    } else {
        r.frame_convention = proto::FrameConvention::Map as i32;
    }
}

/// Bring a request's prior, given in `convention`, into the map's own convention (its pose and
/// covariance); a MAP prior is left as it is. A pose without rotation is read as the identity.
pub fn prior_to_map(
    prior: &mut proto::Prior,
    convention: proto::FrameConvention,
    frames: MapFrames,
) {
    if convention != proto::FrameConvention::Ros {
        return;
    }
    if let Some(p) = prior.pose.as_mut() {
        // Only the position is used today; a missing or degenerate rotation is read as none.
        let q = p
            .rotation
            .map(|r| Quaternion::new(r.w, r.x, r.y, r.z))
            .filter(|q| q.norm().is_finite() && q.norm() > 1e-9)
            .map_or_else(UnitQuaternion::identity, UnitQuaternion::from_quaternion);
        if let Some(t) = p.translation {
            let ros = Isometry3::from_parts(Translation3::new(t.x, t.y, t.z), q);
            *p = to_proto_pose(&ros_to_map(&ros, frames.up, frames.camera));
        }
    }
    let back = ros_from_map_world(frames.up).inverse();
    if let Some(c) = rotate_covariance(&prior.covariance, &back) {
        prior.covariance = c;
    }
}

#[cfg(test)]
mod cause_tests {
    use super::*;

    #[test]
    fn every_cause_keeps_its_name_on_the_wire_and_in_the_metrics() {
        for c in Cause::ALL {
            let wire = cause_message(Some(c)) as i32;
            assert_eq!(cause_label(wire), c.name());
            assert_eq!(cause_name(wire), c.name());
        }
        assert_eq!(cause_label(cause_message(None) as i32), "");
        assert_eq!(cause_name(0), "NO_MATCH");
    }
}
