//! Where the robot roughly is: a search region in the map frame, the spatial index that finds the map
//! images inside it, and the path ([`Mode`]) that produced an answer.
//!
//! A robot rarely starts from nothing: wheel odometry or its last fix puts it within a metre or two.
//! Restricting retrieval to the map images taken there removes every look-alike elsewhere in a large
//! map (the failure of global retrieval on maps of many similar rooms) and costs less. A prior never
//! decides a pose: the restricted candidates go through the same registration and verification, and a
//! region where nothing verifies falls back to global retrieval ([`crate::pipeline::Pipeline::localize_with`]).

use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{UnitQuaternion, Vector3};
use serde::Serialize;

use crate::odometry::Keyframe;
use crate::PipelineError;

/// Largest radius a region may have, metres (a "prior" bigger than a campus is no prior).
pub const MAX_RADIUS_M: f64 = 10_000.0;
/// How many standard deviations of position a covariance-only prior's radius spans.
pub const COVARIANCE_SIGMAS: f64 = 3.0;
/// Radius of a tracking region right after the last verified pose, metres.
pub const TRACKING_BASE_RADIUS_M: f64 = 1.0;
/// How fast the tracking region grows with the time since the last verified pose, metres per second
/// (a brisk indoor robot or a walking person).
pub const TRACKING_SPEED_MPS: f64 = 1.5;
/// A stream's last pose older than this, seconds, no longer makes a tracking region.
pub const TRACKING_MAX_AGE_S: f64 = 5.0;
/// Largest turn of a tracked camera right after its last verified pose, degrees.
pub const TRACKING_BASE_TURN_DEG: f64 = 30.0;
/// How fast that bound grows with the time since the last verified pose, degrees per second (a robot
/// turning on the spot, or a hand-held camera panning).
pub const TRACKING_TURN_DEG_PER_S: f64 = 90.0;
/// Candidates matched while tracking (the last pose leaves few plausible views).
pub const TRACKING_CANDIDATES: usize = 2;
/// Edge of the spatial index's cells, metres (about a room).
const CELL_M: f64 = 2.0;

/// Which path answered a query.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Default)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum Mode {
    /// Retrieval over the whole map.
    #[default]
    Global,
    /// Retrieval among the map images inside the caller's prior region.
    Prior,
    /// Retrieval among the map images near a stream's last verified pose.
    Tracking,
}

impl Mode {
    /// The proto/JSON name: `GLOBAL`, `PRIOR`, `TRACKING`.
    pub fn name(self) -> &'static str {
        match self {
            Mode::Global => "GLOBAL",
            Mode::Prior => "PRIOR",
            Mode::Tracking => "TRACKING",
        }
    }
}

/// A sphere in the map frame where the query camera is expected to be.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    /// Centre, map frame, metres.
    pub center_m: Vector3<f64>,
    /// Radius, metres (positive, at most [`MAX_RADIUS_M`]).
    pub radius_m: f64,
}

impl Region {
    /// A region from a centre and a radius; `Query` error for non-finite values or a radius outside
    /// (0, [`MAX_RADIUS_M`]].
    pub fn new(center_m: Vector3<f64>, radius_m: f64) -> Result<Self, PipelineError> {
        if !center_m.iter().all(|v| v.is_finite()) {
            return Err(PipelineError::Query(format!(
                "prior: position ({}, {}, {}) is not finite",
                center_m.x, center_m.y, center_m.z
            )));
        }
        if !(radius_m.is_finite() && radius_m > 0.0 && radius_m <= MAX_RADIUS_M) {
            return Err(PipelineError::Query(format!(
                "prior: radius {radius_m} m is not in (0, {MAX_RADIUS_M}] m"
            )));
        }
        Ok(Self { center_m, radius_m })
    }

    /// A region from a position and its 6x6 pose covariance (row-major, ROS order x, y, z, rotation
    /// about x, y, z; metres² and radians²): radius = [`COVARIANCE_SIGMAS`] times the square root of the
    /// largest eigenvalue of the position block. `Query` error for a wrong length, non-finite values, a
    /// negative position variance or a zero-size region.
    pub fn from_covariance(
        center_m: Vector3<f64>,
        covariance: &[f64],
    ) -> Result<Self, PipelineError> {
        if covariance.len() != 36 {
            return Err(PipelineError::Query(format!(
                "prior: covariance has {} values, expected 36 (6x6 row-major)",
                covariance.len()
            )));
        }
        if !covariance.iter().all(|v| v.is_finite()) {
            return Err(PipelineError::Query(
                "prior: covariance holds a non-finite value".into(),
            ));
        }
        if let Some(i) = (0..6).find(|&i| covariance[i * 7] < 0.0) {
            return Err(PipelineError::Query(format!(
                "prior: covariance diagonal element {i} is negative ({})",
                covariance[i * 7]
            )));
        }
        let block = nalgebra::Matrix3::from_fn(|r, c| {
            0.5 * (covariance[r * 6 + c] + covariance[c * 6 + r])
        });
        let largest = block.symmetric_eigenvalues().max().max(0.0);
        Self::new(center_m, COVARIANCE_SIGMAS * largest.sqrt())
    }

    /// True when `p` (map frame, metres) is inside.
    pub fn contains(&self, p: &Vector3<f64>) -> bool {
        (p - self.center_m).norm_squared() <= self.radius_m * self.radius_m
    }
}

/// The region a stream tracks in: around its last verified position (map frame, metres), widened by
/// how far the camera can have moved in `elapsed_s` seconds; `None` once the pose is older than
/// [`TRACKING_MAX_AGE_S`] (the stream relocalises globally).
pub fn tracking_region(last_position_m: Vector3<f64>, elapsed_s: f64) -> Option<Region> {
    if !(0.0..=TRACKING_MAX_AGE_S).contains(&elapsed_s) {
        return None;
    }
    Region::new(
        last_position_m,
        TRACKING_BASE_RADIUS_M + TRACKING_SPEED_MPS * elapsed_s,
    )
    .ok()
}

/// The orientations a tracked camera can have: within `max_deg` of its last verified orientation.
/// A camera cannot turn round in a fraction of a second; a room's symmetry can make a pose that does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Heading {
    /// Rotation of the last verified `world_from_camera` (map frame, map camera axes).
    pub rotation: UnitQuaternion<f64>,
    /// Largest geodesic angle from it, degrees.
    pub max_deg: f64,
}

impl Heading {
    /// The angle, degrees, by which `rotation` (same frame and axes) turns away from the last one,
    /// when it is more than allowed.
    pub fn exceeded_by(&self, rotation: &UnitQuaternion<f64>) -> Option<f64> {
        let deg = self.rotation.angle_to(rotation).to_degrees();
        (deg > self.max_deg).then_some(deg)
    }
}

/// The heading bound of a stream whose last verified pose had `rotation`, `elapsed_s` seconds ago:
/// [`TRACKING_BASE_TURN_DEG`] plus [`TRACKING_TURN_DEG_PER_S`] per second.
pub fn tracking_heading(rotation: UnitQuaternion<f64>, elapsed_s: f64) -> Heading {
    Heading {
        rotation,
        max_deg: TRACKING_BASE_TURN_DEG + TRACKING_TURN_DEG_PER_S * elapsed_s.max(0.0),
    }
}

/// A uniform grid over the map images' camera positions: the images inside a region in time
/// proportional to the cells the region touches, not to the map's size.
#[derive(Debug, Clone, Default)]
pub struct PoseIndex {
    positions: Vec<Vector3<f64>>,
    cells: HashMap<[i64; 3], Vec<u32>>,
}

fn cell_of(p: &Vector3<f64>) -> [i64; 3] {
    [
        (p.x / CELL_M).floor() as i64,
        (p.y / CELL_M).floor() as i64,
        (p.z / CELL_M).floor() as i64,
    ]
}

impl PoseIndex {
    /// Index camera positions (map frame, metres), ids = their order. Non-finite positions are left out.
    pub fn new(positions: Vec<Vector3<f64>>) -> Self {
        let mut cells: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
        for (i, p) in positions.iter().enumerate() {
            if p.iter().all(|v| v.is_finite()) {
                cells.entry(cell_of(p)).or_default().push(i as u32);
            }
        }
        Self { positions, cells }
    }

    /// Ids of the positions inside `region`, nearest first (ties by id).
    pub fn within(&self, region: &Region) -> Vec<usize> {
        let lo = cell_of(&region.center_m.add_scalar(-region.radius_m));
        let hi = cell_of(&region.center_m.add_scalar(region.radius_m));
        let span: i64 = (0..3).map(|a| hi[a] - lo[a] + 1).product();
        let mut found: Vec<(f64, usize)> = Vec::new();
        let mut take = |ids: &[u32]| {
            for &i in ids {
                let p = &self.positions[i as usize];
                if region.contains(p) {
                    found.push(((p - region.center_m).norm(), i as usize));
                }
            }
        };
        if span <= 0 || span as usize > self.cells.len() {
            // A region wider than the occupied cells: walking the cells is cheaper.
            for ids in self.cells.values() {
                take(ids);
            }
        } else {
            for x in lo[0]..=hi[0] {
                for y in lo[1]..=hi[1] {
                    for z in lo[2]..=hi[2] {
                        if let Some(ids) = self.cells.get(&[x, y, z]) {
                            take(ids);
                        }
                    }
                }
            }
        }
        found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        found.into_iter().map(|(_, i)| i).collect()
    }
}

/// How to localise one query beyond the frame itself.
#[derive(Debug, Clone, Default)]
pub struct LocalizeOptions {
    /// Try the map images inside this region first.
    pub region: Option<Region>,
    /// What the region is: [`Mode::Prior`] (the caller's) or [`Mode::Tracking`] (a stream's last pose).
    pub region_mode: Mode,
    /// Candidates to match among the region's images (`None`: the preset's shortlist).
    pub region_candidates: Option<usize>,
    /// Tracking only: the orientations the camera can have; a pose outside is never answered.
    pub heading: Option<Heading>,
    /// A stream's keyframe: the frame is registered against it ([`crate::odometry`]) before the map
    /// is tried (see `map_first`).
    pub keyframe: Option<Arc<Keyframe>>,
    /// Let the map (region, then global) answer before the keyframe, whose hop then judges the map's
    /// answer: the stream's map fix is getting old and the chain should be re-anchored.
    pub map_first: bool,
    /// Return the keyframe the next frame of the stream should track from
    /// ([`crate::pipeline::Localization::keyframe`]).
    pub want_keyframe: bool,
    /// Only these map images (indices, ascending) may be retrieved, in the region and globally: the
    /// rest of the map is held out (`pntr_mapping::selfcal` localizes a region's frames against the
    /// others). Verification's nearby views come from the matched image's place and the retrieved
    /// images, so holding out whole places keeps it out of verification too. `None`: every image.
    pub among: Option<Arc<[usize]>>,
}

impl LocalizeOptions {
    /// Search `region` first as a caller's prior.
    pub fn prior(region: Region) -> Self {
        Self {
            region: Some(region),
            region_mode: Mode::Prior,
            ..Self::default()
        }
    }

    /// Search `region` first as a stream's tracking region: [`TRACKING_CANDIDATES`] candidates, and a
    /// global answer outside the region is refused.
    pub fn tracking(region: Region) -> Self {
        Self {
            region: Some(region),
            region_mode: Mode::Tracking,
            region_candidates: Some(TRACKING_CANDIDATES),
            ..Self::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_finds_exactly_the_positions_inside_the_region() {
        // A pseudo-random cloud over 60 m, compared with a linear scan for many regions.
        let mut s = 12345u64;
        let mut r = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let pts: Vec<Vector3<f64>> = (0..2000)
            .map(|_| Vector3::new(60.0 * r() - 30.0, 3.0 * r(), 60.0 * r() - 30.0))
            .collect();
        let index = PoseIndex::new(pts.clone());
        for k in 0..200 {
            let c = Vector3::new(70.0 * r() - 35.0, 3.0 * r(), 70.0 * r() - 35.0);
            let radius = if k % 10 == 0 { 100.0 } else { 0.2 + 4.0 * r() };
            let region = Region::new(c, radius).unwrap();
            let got = index.within(&region);
            let mut want: Vec<usize> = (0..pts.len())
                .filter(|&i| region.contains(&pts[i]))
                .collect();
            let mut sorted = got.clone();
            sorted.sort();
            want.sort();
            assert_eq!(sorted, want, "region {k}");
            for w in got.windows(2) {
                assert!(
                    (pts[w[0]] - c).norm() <= (pts[w[1]] - c).norm(),
                    "nearest first"
                );
            }
        }
    }

    #[test]
    fn covariance_radius_is_three_sigma_of_the_widest_axis() {
        let mut cov = [0.0; 36];
        cov[0] = 0.04; // sigma_x 0.2 m
        cov[7] = 0.25; // sigma_y 0.5 m
        cov[14] = 0.01;
        cov[21] = 1.0; // rotation variances do not widen the region
        let r = Region::from_covariance(Vector3::zeros(), &cov).unwrap();
        assert!((r.radius_m - 1.5).abs() < 1e-9, "{}", r.radius_m);
        assert!(Region::from_covariance(Vector3::zeros(), &cov[..35]).is_err());
        cov[7] = -1.0;
        let e = Region::from_covariance(Vector3::zeros(), &cov).unwrap_err();
        assert!(e.to_string().contains("negative"), "{e}");
        assert!(
            Region::from_covariance(Vector3::zeros(), &[0.0; 36]).is_err(),
            "zero region"
        );
        assert!(Region::new(Vector3::new(f64::NAN, 0.0, 0.0), 1.0).is_err());
        assert!(Region::new(Vector3::zeros(), -1.0).is_err());
        assert!(Region::new(Vector3::zeros(), 1e9).is_err());
    }
}
