//! HPointLoc's capture protocol applied to a generated scene: key positions on a 2 m grid in free
//! space, six database views per key position, and queries sampled around it.

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::seq::SliceRandom;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

use crate::scene::{Rect, Scene};

/// Spacing of the key-position grid, metres.
pub const GRID_M: f32 = 2.0;
/// Camera height above the floor, metres.
pub const CAMERA_HEIGHT_M: f64 = 1.25;
/// Queries are drawn uniformly within this distance of their key position, metres.
pub const QUERY_RADIUS_M: f64 = 0.5;
/// A key position needs this much horizontal clearance from walls and furniture, metres, so that the
/// disc its queries are drawn from is mostly free.
pub const KEY_CLEARANCE_M: f32 = 0.35;
/// A query camera needs this much clearance: a camera body cannot be inside or touching geometry.
pub const QUERY_CLEARANCE_M: f32 = 0.15;
/// Number of database views per key position (yaw 0, 60, ..., 300 degrees).
pub const DB_VIEWS: usize = 6;

/// The poses planned for one Point.
#[derive(Debug, Clone)]
pub struct PointPlan {
    /// Key position (x, z) on the floor, metres.
    pub key_xz: (f64, f64),
    /// `world_from_camera` (Habitat axes) of the six database views.
    pub db: Vec<Isometry3<f64>>,
    /// `world_from_camera` (Habitat axes) of the accepted queries.
    pub queries: Vec<Isometry3<f64>>,
    /// Query poses drawn but discarded because they were not in free space.
    pub discarded: usize,
}

/// Camera rotation (Habitat axes) from yaw about world y, then pitch about the camera x, then roll
/// about the camera z; all in radians. Yaw 0 looks along world -z.
pub fn camera_rotation(yaw: f64, pitch: f64, roll: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), pitch)
        * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll)
}

/// Candidate key positions of a scene: grid nodes (offset drawn from `rng`) with enough clearance.
pub fn key_positions(scene: &Scene, obstacles: &[Rect], rng: &mut ChaCha8Rng) -> Vec<(f32, f32)> {
    let ox = rng.gen_range(0.3..GRID_M - 0.3);
    let oz = rng.gen_range(0.3..GRID_M - 0.3);
    let mut out = Vec::new();
    let mut z = oz;
    while z < scene.depth_m {
        let mut x = ox;
        while x < scene.width_m {
            if Scene::clearance(obstacles, scene.width_m, scene.depth_m, x, z) >= KEY_CLEARANCE_M {
                out.push((x, z));
            }
            x += GRID_M;
        }
        z += GRID_M;
    }
    out
}

/// Plan the views of one key position.
///
/// Query orientation: yaw uniform in 0..360 degrees; pitch and roll Gaussian with `tilt_sigma_deg`
/// (default 2 degrees), clipped at three sigma: HPointLoc's published errors suggest mostly-upright
/// queries, and a hand-held or robot camera is never perfectly level.
pub fn plan_point(
    key: (f32, f32),
    scene: &Scene,
    obstacles: &[Rect],
    queries: usize,
    tilt_sigma_deg: f64,
    rng: &mut ChaCha8Rng,
) -> PointPlan {
    let (kx, kz) = (key.0 as f64, key.1 as f64);
    let db = (0..DB_VIEWS)
        .map(|k| {
            Isometry3::from_parts(
                Translation3::new(kx, CAMERA_HEIGHT_M, kz),
                camera_rotation((k as f64 * 60.0).to_radians(), 0.0, 0.0),
            )
        })
        .collect();
    let tilt = Normal::new(0.0, tilt_sigma_deg.max(0.0)).expect("finite sigma");
    let clip = 3.0 * tilt_sigma_deg.max(0.0);
    let mut out = Vec::with_capacity(queries);
    let mut discarded = 0;
    // Each of the M draws is kept or discarded, as in the protocol: no redraws.
    for _ in 0..queries {
        let r = QUERY_RADIUS_M * rng.gen::<f64>().sqrt();
        let a = rng.gen_range(0.0..std::f64::consts::TAU);
        let (x, z) = (kx + r * a.cos(), kz + r * a.sin());
        let yaw = rng.gen_range(0.0..std::f64::consts::TAU);
        let pitch = tilt.sample(rng).clamp(-clip, clip).to_radians();
        let roll = tilt.sample(rng).clamp(-clip, clip).to_radians();
        if Scene::clearance(obstacles, scene.width_m, scene.depth_m, x as f32, z as f32)
            < QUERY_CLEARANCE_M
        {
            discarded += 1;
            continue;
        }
        out.push(Isometry3::from_parts(
            Translation3::new(x, CAMERA_HEIGHT_M, z),
            camera_rotation(yaw, pitch, roll),
        ));
    }
    PointPlan {
        key_xz: (kx, kz),
        db,
        queries: out,
        discarded,
    }
}

/// Keep `k` of the candidates, chosen at random, in their original (row-major grid) order.
pub fn choose_points(
    mut candidates: Vec<(f32, f32)>,
    k: usize,
    rng: &mut ChaCha8Rng,
) -> Vec<(f32, f32)> {
    if candidates.len() <= k {
        return candidates;
    }
    let mut idx: Vec<usize> = (0..candidates.len()).collect();
    idx.shuffle(rng);
    idx.truncate(k);
    idx.sort_unstable();
    let keep: std::collections::HashSet<usize> = idx.into_iter().collect();
    let mut i = 0;
    candidates.retain(|_| {
        i += 1;
        keep.contains(&(i - 1))
    });
    candidates
}
