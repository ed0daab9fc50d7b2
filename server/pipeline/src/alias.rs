//! Texture aliasing: a registration that locked onto a repeated texture one period off.
//!
//! Floor tiles, a carpet's pattern, tiled or papered walls repeat every few tens of centimetres. When
//! a frame's distinctive matches are few (blur, sensor noise, a plain room), the largest rigidly
//! consistent set of matches can be the repeated texture matched to its neighbouring copy: a pose
//! whose rotation is right and whose position is off by one period (0.3-0.7 m) along the textured
//! surface. Such a set is as consistent as the right one, so neither the maximum clique nor the dense
//! refinement (a local method) can leave it; but the matches that did land on the right copies, and
//! the matches on everything that does not repeat, all disagree with it by the same translation. So:
//!
//! 1. Every matched pair's residual under the registered pose, `dst - db_from_query * src` (map view
//!    frame, metres), is taken; the residuals of matches that disagree by one common translation
//!    gather in one place ([`translation_modes`]: the densest balls of radius `bound`, between
//!    [`MIN_SHIFT_M`] and [`MAX_SHIFT_M`] from the pose, with as many matches as a registration
//!    needs inliers).
//! 2. Each mode is a rival pose: the registered pose moved by that translation, refitted (least
//!    squares) to the pairs within `bound` of it, which are its inliers.
//! 3. The dense checks of both directions against the matched map view decide ([`resolve`]): the
//!    rival replaces the registered pose when a larger share of the query's samples agrees with the
//!    view's depth and fewer see through its surfaces, or, the depth no worse, the grey values
//!    correlate better within small tiles; the repeated texture itself looks the same either way, the
//!    walls, furniture and the texture's edges do not.
//!
//! This is a hypothesis test between a few discrete poses, like the alias search of the answer's
//! covariance ([`crate::verify::aliases`]), which widens the covariance when such a shift explains the
//! frame as well; here the shift is found from the matches, so it needs no search over a grid of
//! shifts.

use std::collections::HashMap;

use nalgebra::{Isometry3, Point3, Translation3, Vector3};

use pntr_registration::kabsch;

use crate::verify::{dense_check_both, DenseCounts, Thumb};

/// Nearest a mode may lie to the registered pose, metres: closer residuals are the registration's own
/// noise (and what the dense refinement corrects).
pub const MIN_SHIFT_M: f64 = 0.15;
/// Farthest, metres: a texture's period in a room (two periods of a 0.35 m tile).
pub const MAX_SHIFT_M: f64 = 1.0;
/// How many modes are tried at most, densest first.
pub const MAX_MODES: usize = 3;

/// A pose the matches support besides the registered one.
#[derive(Debug, Clone)]
pub struct Mode {
    /// The translation (map view frame, metres) that moves the registered pose onto this one.
    pub shift: Vector3<f64>,
    /// Indices of the pairs whose residual lies in the mode's ball and in no denser mode's (not the
    /// rival's inliers, which [`resolve`] counts around the mean shift).
    pub support: Vec<usize>,
}

/// The densest translations among the residuals `dst[i] - db_from_query * src[i]`: balls of radius
/// `bound_m` centred on a residual, between [`MIN_SHIFT_M`] and [`MAX_SHIFT_M`] long, with at least
/// `min_support` residuals, densest first, at most [`MAX_MODES`], no pair in two modes. The shift
/// is the mean of the ball's residuals. `src` and `dst` are parallel (query camera and map view
/// frames, metres).
pub fn translation_modes(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    db_from_query: &Isometry3<f64>,
    bound_m: f64,
    min_support: usize,
) -> Vec<Mode> {
    let min_support = min_support.max(1);
    debug_assert_eq!(src.len(), dst.len(), "src and dst are parallel");
    let residuals: Vec<(usize, Vector3<f64>)> = src
        .iter()
        .zip(dst)
        .map(|(s, d)| d - (db_from_query * Point3::from(*s)).coords)
        .enumerate()
        .filter(|(_, r)| {
            let n = r.norm();
            (MIN_SHIFT_M - bound_m..=MAX_SHIFT_M + bound_m).contains(&n)
        })
        .collect();
    if residuals.len() < min_support || bound_m <= 0.0 {
        return Vec::new();
    }
    // Cells of the ball's radius: a ball's members lie in its centre's cell or the 26 around it.
    let cell = |r: &Vector3<f64>| {
        (
            (r.x / bound_m).floor() as i64,
            (r.y / bound_m).floor() as i64,
            (r.z / bound_m).floor() as i64,
        )
    };
    let mut grid: HashMap<(i64, i64, i64), Vec<usize>> = HashMap::new();
    for (k, (_, r)) in residuals.iter().enumerate() {
        grid.entry(cell(r)).or_default().push(k);
    }
    let ball = |centre: &Vector3<f64>| -> Vec<usize> {
        let (cx, cy, cz) = cell(centre);
        let mut out = Vec::new();
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(ks) = grid.get(&(cx + dx, cy + dy, cz + dz)) {
                        out.extend(
                            ks.iter()
                                .copied()
                                .filter(|&k| (residuals[k].1 - centre).norm() <= bound_m),
                        );
                    }
                }
            }
        }
        out
    };
    let mut balls: Vec<(usize, Vec<usize>)> = residuals
        .iter()
        .enumerate()
        .filter(|(_, (_, r))| (MIN_SHIFT_M..=MAX_SHIFT_M).contains(&r.norm()))
        .map(|(k, (_, r))| (k, ball(r)))
        .filter(|(_, b)| b.len() >= min_support)
        .collect();
    // Densest first; ties by the centre's index, so the result does not depend on hashing.
    balls.sort_by(|a, b| b.1.len().cmp(&a.1.len()).then(a.0.cmp(&b.0)));
    let mut taken = vec![false; residuals.len()];
    let mut modes = Vec::new();
    for (centre, members) in balls {
        if modes.len() == MAX_MODES {
            break;
        }
        // A ball centred inside a denser mode is its fringe, not another translation.
        if taken[centre] {
            continue;
        }
        let free: Vec<usize> = members.into_iter().filter(|&k| !taken[k]).collect();
        if free.len() < min_support {
            continue;
        }
        let shift = free.iter().map(|&k| residuals[k].1).sum::<Vector3<f64>>() / free.len() as f64;
        for &k in &free {
            taken[k] = true;
        }
        modes.push(Mode {
            shift,
            support: free.iter().map(|&k| residuals[k].0).collect(),
        });
    }
    modes
}

/// A registered pose replaced by the rival its matches support.
#[derive(Debug, Clone)]
pub struct Resolved {
    /// The rival pose, query camera to map view camera (OpenCV axes, metres).
    pub db_from_query: Isometry3<f64>,
    /// Indices of the pairs within `bound_m` of it (its inliers).
    pub inliers: Vec<usize>,
}

/// Agreeing share (of the samples inside the view) a rival must gain to win on depth.
pub const DEPTH_MARGIN: f64 = 0.05;
/// Local grey correlation a rival that wins on depth may lose.
pub const GREY_SLACK: f64 = 0.05;
/// Local grey correlation a rival must gain to win on grey alone, its depth no worse.
pub const GREY_MARGIN: f64 = 0.08;

/// Whether the dense checks prefer `rival` to `current`. On depth: a share of agreeing samples
/// higher by [`DEPTH_MARGIN`] with a smaller share of free-space violations (the walls and furniture
/// of the right copy stand where the map saw them) and the local grey correlation
/// ([`DenseCounts::local_gray_correlation`]) no worse by more than [`GREY_SLACK`]. On grey, where the
/// depth cannot tell (a shift along a flat wall): no more violations, no smaller agreeing share and a
/// local grey correlation higher by [`GREY_MARGIN`]. Agreement as shares, not counts: a shift that
/// moves part of the frame out of the view loses samples either way (the grey test's "no more
/// violations" counts them, as measured). Chosen by measurement (BENCHMARKS.md,
/// "Registrations one texture period off"): against each alternative pose of the demo scene's robot
/// captures and the truth, and end to end against depth alone, violation counts, and any gain in
/// agreeing count and grey correlation.
fn better(rival: &DenseCounts, current: &DenseCounts) -> bool {
    let (ra, ca) = (rival.agree_share(), current.agree_share());
    let (rl, cl) = (
        rival.local_gray_correlation(),
        current.local_gray_correlation(),
    );
    let on_depth = ra > ca + DEPTH_MARGIN
        && rival.violate_share() < current.violate_share()
        && rl >= cl - GREY_SLACK;
    let on_grey = rival.violate <= current.violate && ra >= ca && rl > cl + GREY_MARGIN;
    on_depth || on_grey
}

/// Test the rival poses of [`translation_modes`] against the registered `db_from_query` with the
/// dense checks of both directions between the query's thumbnail `query` and the matched map view's
/// `db`, densest mode first, each against the pose that has won so far; return the last winner, or
/// `None` to keep the registration. A rival needs `min_support` inliers (the pairs within `bound_m` of
/// it), as a registration does. `src` and `dst` are all the matched pairs (parallel; query camera and
/// map view frames, metres), `bound_m` the registration's fixed noise bound (also for a candidate
/// registered with bounds grown by the frame's depth noise: measured as it is).
pub fn resolve(
    query: &Thumb,
    db: &Thumb,
    db_from_query: &Isometry3<f64>,
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    bound_m: f64,
    min_support: usize,
) -> Option<Resolved> {
    let modes = translation_modes(src, dst, db_from_query, bound_m, min_support);
    if modes.is_empty() {
        return None;
    }
    let within = |pose: &Isometry3<f64>| -> Vec<usize> {
        src.iter()
            .zip(dst)
            .enumerate()
            .filter(|(_, (s, d))| (*d - (pose * Point3::from(**s)).coords).norm() <= bound_m)
            .map(|(i, _)| i)
            .collect()
    };
    let mut best = dense_check_both(query, db, db_from_query);
    let mut chosen = None;
    for m in modes {
        // The registration moved by the mode's mean shift, then the least-squares pose of the pairs
        // within the bound of it (the rotation too: the registration's was fitted to the aliased
        // pairs), kept when as many pairs support it.
        let shifted = Translation3::from(m.shift) * db_from_query;
        let near = within(&shifted);
        if near.len() < min_support {
            continue;
        }
        let (s_in, d_in): (Vec<_>, Vec<_>) = near.iter().map(|&i| (src[i], dst[i])).unzip();
        let fitted = kabsch(&s_in, &d_in)
            .map(|r| r.to_isometry())
            .map(|p| (within(&p), p))
            .filter(|(inl, _)| inl.len() >= min_support);
        let (inliers, pose) = fitted.unwrap_or((near, shifted));
        let counts = dense_check_both(query, db, &pose);
        if better(&counts, &best) {
            best = counts;
            chosen = Some(Resolved {
                db_from_query: pose,
                inliers,
            });
        }
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_scenes::room_view;
    use nalgebra::UnitQuaternion;

    /// One period of a floor texture, metres (map view frame).
    fn period() -> Vector3<f64> {
        Vector3::new(0.35, 0.0, 0.0)
    }

    /// The right pose of the query camera in the map view's frame (the map view at the room's origin).
    fn truth() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.2, 0.0, 0.5),
            UnitQuaternion::from_euler_angles(0.0, 0.15, 0.0),
        )
    }

    /// `n` points on the room's floor (y = 1.2 m) in front of the query camera, in its frame.
    fn floor_points(n: usize) -> Vec<Vector3<f64>> {
        let room_from_query = truth();
        (0..n)
            .map(|i| {
                let room = Point3::new(
                    -1.5 + 3.0 * (i % 7) as f64 / 6.0,
                    1.2,
                    1.5 + 2.0 * (i / 7) as f64 / 5.0,
                );
                (room_from_query.inverse() * room).coords
            })
            .collect()
    }

    /// Pairs of which the first `aliased` lie one period off the truth and the rest on it.
    fn pairs(aliased: usize, right: usize) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
        let src = floor_points(aliased + right);
        let dst = src
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let d = (truth() * Point3::from(*s)).coords;
                if i < aliased {
                    d - period()
                } else {
                    d
                }
            })
            .collect();
        (src, dst)
    }

    #[test]
    fn a_rival_wins_on_depth_or_on_grey_within_tiles_and_not_on_less() {
        let current = DenseCounts::of(1000, 800, 100, 0.5);
        // Depth: a higher agreeing share with fewer violations, grey within tiles a little worse.
        assert!(better(&DenseCounts::of(1000, 900, 50, 0.46), &current));
        // ... but not with more violations, a share only 4 points higher, or grey much worse.
        assert!(!better(&DenseCounts::of(1000, 900, 110, 0.5), &current));
        assert!(!better(&DenseCounts::of(1000, 840, 50, 0.5), &current));
        assert!(!better(&DenseCounts::of(1000, 900, 50, 0.4), &current));
        // Shares, not counts: half the samples inside the view, fewer of them agreeing, a higher share.
        assert!(better(&DenseCounts::of(500, 450, 20, 0.5), &current));
        // Grey alone: the depth no worse and grey within tiles higher by more than the margin...
        assert!(better(&DenseCounts::of(1000, 800, 100, 0.6), &current));
        // ... not by less, and not with more violations or a smaller agreeing share.
        assert!(!better(&DenseCounts::of(1000, 800, 100, 0.55), &current));
        assert!(!better(&DenseCounts::of(1000, 800, 101, 0.6), &current));
        assert!(!better(&DenseCounts::of(1000, 790, 100, 0.6), &current));
    }

    #[test]
    fn the_matches_off_by_one_period_gather_in_one_mode() {
        let (src, dst) = pairs(25, 8);
        // Registered on the 25 aliased pairs: the 8 right ones are one period away.
        let wrong = Translation3::from(-period()) * truth();
        let modes = translation_modes(&src, &dst, &wrong, 0.05, 8);
        assert_eq!(modes.len(), 1, "{modes:?}");
        assert!((modes[0].shift - period()).norm() < 1e-9, "{modes:?}");
        let mut support = modes[0].support.clone();
        support.sort_unstable();
        assert_eq!(support, (25..33).collect::<Vec<_>>());
        // Fewer disagreeing pairs than a registration needs make no mode.
        assert!(translation_modes(&src, &dst, &wrong, 0.05, 9).is_empty());
    }

    #[test]
    fn a_registration_one_period_off_moves_onto_the_copy_the_walls_confirm() {
        let db = room_view(&Isometry3::identity());
        let query = room_view(&truth());
        let (src, dst) = pairs(25, 8);
        let wrong = Translation3::from(-period()) * truth();
        let r = resolve(&query, &db, &wrong, &src, &dst, 0.05, 8).expect("moved");
        let off = (r.db_from_query.translation.vector - truth().translation.vector).norm();
        assert!(off < 1e-6, "{off} m from the truth");
        assert!(r.db_from_query.rotation.angle_to(&truth().rotation) < 1e-9);
        assert_eq!(r.inliers, (25..33).collect::<Vec<_>>());
    }

    #[test]
    fn a_right_registration_stays_where_it_is_despite_aliased_matches() {
        let db = room_view(&Isometry3::identity());
        let query = room_view(&truth());
        // 8 aliased pairs, 25 right: registered on the right ones.
        let (src, dst) = pairs(8, 25);
        let modes = translation_modes(&src, &dst, &truth(), 0.05, 8);
        assert_eq!(modes.len(), 1, "the aliased pairs make a rival: {modes:?}");
        assert!(resolve(&query, &db, &truth(), &src, &dst, 0.05, 8).is_none());
    }
}
