//! A TF tree as a recording holds it (`/tf` and `/tf_static`: `geometry_msgs/TransformStamped` with
//! `header.frame_id` = parent, `child_frame_id` = child, `transform` = parent_from_child), looked up
//! at any stamp: each dynamic edge interpolated between the samples around the stamp (linear
//! translation, slerp rotation; [`crate::tum::Trajectory::at`]), static edges at any time.

use std::collections::HashMap;

use nalgebra::Isometry3;

use crate::tum::Trajectory;

/// Longest gap between two samples of a dynamic transform that a look-up interpolates across,
/// seconds (tf2's default buffer length: a `map -> odom` published at 1 Hz or slower still holds).
pub const TF_MAX_GAP_S: f64 = 10.0;

enum Edge {
    Static(Isometry3<f64>),
    Dynamic(Vec<(f64, Isometry3<f64>)>),
}

/// One parent of a frame and the transforms published under it.
struct Link {
    parent: String,
    edge: Edge,
    /// Transforms recorded under this parent.
    samples: usize,
}

/// The transforms of a recording. A frame normally has one parent; one published under two (two
/// publishers, say `odom -> base_link` from odometry and `map -> base_link` from another localizer)
/// keeps both apart: a look-up follows one chain, never a mix ([`TfTree::several_parents`]).
#[derive(Default)]
pub struct TfTree {
    /// child -> its parents, in the order first seen.
    edges: HashMap<String, Vec<Link>>,
    /// Dynamic edges as trajectories by (child, parent), built by [`TfTree::seal`].
    sealed: HashMap<(String, String), Trajectory>,
}

impl TfTree {
    /// Add `parent_from_child` at `stamp` seconds (`is_static`: from `/tf_static`, valid at any time;
    /// it replaces dynamic samples of the same edge).
    pub fn add(
        &mut self,
        parent: &str,
        child: &str,
        stamp: f64,
        parent_from_child: Isometry3<f64>,
        is_static: bool,
    ) {
        let parent = parent.trim_start_matches('/').to_string();
        let child = child.trim_start_matches('/').to_string();
        let links = self.edges.entry(child).or_default();
        let link = match links.iter().position(|l| l.parent == parent) {
            Some(i) => &mut links[i],
            None => {
                links.push(Link {
                    parent,
                    edge: Edge::Dynamic(Vec::new()),
                    samples: 0,
                });
                links.last_mut().expect("just pushed")
            }
        };
        link.samples += 1;
        match (&mut link.edge, is_static) {
            (_, true) => link.edge = Edge::Static(parent_from_child),
            (Edge::Dynamic(v), false) => v.push((stamp, parent_from_child)),
            (Edge::Static(_), false) => {}
        }
        self.sealed.clear();
    }

    /// True without any transform.
    pub fn is_empty(&self) -> bool {
        self.edges.is_empty()
    }

    /// Sort the dynamic edges for look-ups (call after the last [`TfTree::add`]).
    pub fn seal(&mut self) {
        // The samples move into the trajectories (no second copy of a long recording's TF).
        let mut sealed = HashMap::new();
        for (child, links) in self.edges.iter_mut() {
            for l in links.iter_mut() {
                if let Edge::Dynamic(v) = &mut l.edge {
                    sealed.insert(
                        (child.clone(), l.parent.clone()),
                        Trajectory::from_poses(std::mem::take(v)),
                    );
                }
            }
        }
        self.sealed = sealed;
    }

    /// Frames published under more than one parent: (child, [(parent, transforms)]), sorted.
    pub fn several_parents(&self) -> Vec<(String, Vec<(String, usize)>)> {
        let mut v: Vec<_> = self
            .edges
            .iter()
            .filter(|(_, links)| links.len() > 1)
            .map(|(c, links)| {
                let parents = links
                    .iter()
                    .map(|l| (l.parent.clone(), l.samples))
                    .collect();
                (c.clone(), parents)
            })
            .collect();
        v.sort();
        v
    }

    /// Whether `target` is `frame` or above it through any parent. Each frame is visited once, so
    /// a cycle in a broken recording's TF (`a -> b -> a`) or frames with many parents end the search.
    fn reaches(&self, frame: &str, target: &str) -> bool {
        let mut seen = std::collections::BTreeSet::new();
        let mut todo = vec![frame];
        while let Some(f) = todo.pop() {
            if f == target {
                return true;
            }
            if seen.insert(f) {
                todo.extend(
                    self.edges
                        .get(f)
                        .into_iter()
                        .flatten()
                        .map(|l| l.parent.as_str()),
                );
            }
        }
        false
    }

    /// The parent a look-up towards `target` follows above `child`: the only one, else the first
    /// seen of those that lead to `target`, else the first seen.
    pub fn parent_towards(&self, child: &str, target: &str) -> Option<&str> {
        let links = self.edges.get(child.trim_start_matches('/'))?;
        let target = target.trim_start_matches('/');
        links
            .iter()
            .find(|l| links.len() == 1 || self.reaches(&l.parent, target))
            .or(links.first())
            .map(|l| l.parent.as_str())
    }

    /// `root_from_frame` at `t` and the root's name, or why not; through frames with several
    /// parents along the one towards `target`.
    fn to_root(
        &self,
        frame: &str,
        t: f64,
        target: &str,
    ) -> Result<(Isometry3<f64>, String), String> {
        let mut pose = Isometry3::identity();
        let mut at = frame.to_string();
        for _ in 0..64 {
            let Some(parent) = self.parent_towards(&at, target) else {
                return Ok((pose, at));
            };
            let link = self.edges[&at]
                .iter()
                .find(|l| l.parent == parent)
                .expect("a parent of this frame");
            let hop = match &link.edge {
                Edge::Static(p) => *p,
                Edge::Dynamic(_) => {
                    let traj = self
                        .sealed
                        .get(&(at.clone(), parent.to_string()))
                        .ok_or("the TF tree is not sealed")?;
                    traj.at_within(t, TF_MAX_GAP_S).ok_or_else(|| {
                        let (a, b) = traj.span().unwrap_or((f64::NAN, f64::NAN));
                        format!(
                            "no transform {parent} -> {at} at {t:.6} s (recorded from {a:.6} to {b:.6} s, or a gap of more than {TF_MAX_GAP_S} s)"
                        )
                    })?
                }
            };
            pose = hop * pose;
            at = parent.to_string();
        }
        Err(format!("the TF tree has a loop above {frame}"))
    }

    /// `target_from_source` at `t` seconds. Errors name both frames and the stamp: a frame the tree
    /// does not hold, frames in two separate trees, a dynamic edge without samples around `t`.
    pub fn lookup(&self, target: &str, source: &str, t: f64) -> Result<Isometry3<f64>, String> {
        let (target, source) = (
            target.trim_start_matches('/'),
            source.trim_start_matches('/'),
        );
        let known = |f: &str| {
            self.edges.contains_key(f)
                || self
                    .edges
                    .values()
                    .any(|links| links.iter().any(|l| l.parent == f))
        };
        for f in [target, source] {
            if !known(f) {
                return Err(format!(
                    "no transform from {target} to {source} at {t:.6} s: the TF tree has no frame {f} (frames: {})",
                    self.frames().join(", ")
                ));
            }
        }
        let (root_from_source, r1) = self
            .to_root(source, t, target)
            .map_err(|e| format!("no transform from {target} to {source} at {t:.6} s: {e}"))?;
        let (root_from_target, r2) = self
            .to_root(target, t, target)
            .map_err(|e| format!("no transform from {target} to {source} at {t:.6} s: {e}"))?;
        if r1 != r2 {
            return Err(format!(
                "no transform from {target} to {source} at {t:.6} s: {source} hangs below {r1}, {target} below {r2} (two separate TF trees)"
            ));
        }
        Ok(root_from_target.inverse() * root_from_source)
    }

    /// Every frame named, sorted.
    pub fn frames(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .edges
            .iter()
            .flat_map(|(c, links)| {
                std::iter::once(c.clone()).chain(links.iter().map(|l| l.parent.clone()))
            })
            .collect();
        v.sort();
        v.dedup();
        v
    }

    /// The frames directly below `frame`, sorted.
    pub fn children(&self, frame: &str) -> Vec<String> {
        let frame = frame.trim_start_matches('/');
        let mut v: Vec<String> = self
            .edges
            .iter()
            .filter(|(_, links)| links.iter().any(|l| l.parent == frame))
            .map(|(c, _)| c.clone())
            .collect();
        v.sort();
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    #[test]
    fn a_chain_with_static_and_interpolated_edges_composes_and_gaps_are_named() {
        let mut tf = TfTree::default();
        let optical =
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(0.5, -0.5, 0.5, -0.5));
        let base_cam =
            Isometry3::from_parts(Translation3::new(0.1, 0.0, 0.3), UnitQuaternion::identity());
        let cam_opt = Isometry3::from_parts(Translation3::identity(), optical);
        tf.add("base_link", "camera_link", 0.0, base_cam, true);
        tf.add(
            "camera_link",
            "camera_color_optical_frame",
            0.0,
            cam_opt,
            true,
        );
        let odom = |t: f64| {
            Isometry3::from_parts(
                Translation3::new(t, 0.0, 0.0),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.2 * t),
            )
        };
        for i in 0..=10 {
            let t = i as f64 * 0.1;
            tf.add("odom", "/base_link", t, odom(t), false);
        }
        let map_odom = Isometry3::translation(0.5, -0.2, 0.0);
        tf.add("map", "odom", 0.0, map_odom, false);
        tf.add("map", "odom", 2.0, map_odom, false);
        tf.seal();
        // Between samples: interpolated.
        let t = 0.45;
        let want = map_odom * odom(t) * base_cam * cam_opt;
        let got = tf.lookup("map", "camera_color_optical_frame", t).unwrap();
        assert!((got.translation.vector - want.translation.vector).norm() < 1e-9);
        assert!(got.rotation.angle_to(&want.rotation) < 1e-6);
        // Outside the samples: refused, naming both frames and the stamp.
        let e = tf
            .lookup("map", "camera_color_optical_frame", 3.0)
            .unwrap_err();
        assert!(
            e.contains("map") && e.contains("camera_color_optical_frame") && e.contains("3.000000"),
            "{e}"
        );
        let e = tf.lookup("map", "camera_depth_frame", 0.5).unwrap_err();
        assert!(e.contains("no frame camera_depth_frame"), "{e}");
    }

    #[test]
    fn a_frame_under_two_parents_follows_one_chain_and_names_both() {
        // Odometry publishes odom -> base_link, another localizer map -> base_link, both at 10 Hz,
        // interleaved; map -> odom comes from a SLAM at 1 Hz. Neither chain may borrow the other's
        // samples.
        let mut tf = TfTree::default();
        let by_odom = |t: f64| Isometry3::translation(t, 0.0, 0.0);
        let by_map = |t: f64| Isometry3::translation(t, 5.0, 0.0);
        for i in 0..=20 {
            let t = i as f64 * 0.1;
            tf.add("odom", "base_link", t, by_odom(t), false);
            tf.add("map", "base_link", t + 0.05, by_map(t + 0.05), false);
        }
        tf.add(
            "map",
            "odom",
            0.0,
            Isometry3::translation(0.0, 1.0, 0.0),
            false,
        );
        tf.add(
            "map",
            "odom",
            3.0,
            Isometry3::translation(0.0, 1.0, 0.0),
            false,
        );
        tf.add("base_link", "camera", 0.0, Isometry3::identity(), true);
        tf.seal();
        assert_eq!(
            tf.several_parents(),
            vec![(
                "base_link".to_string(),
                vec![("odom".to_string(), 21), ("map".to_string(), 21)]
            )]
        );
        // Towards `map`, both parents lead there: the first seen (odom) is followed throughout.
        assert_eq!(tf.parent_towards("base_link", "map"), Some("odom"));
        let got = tf.lookup("map", "camera", 1.23).unwrap();
        assert!((got.translation.vector - Vector3::new(1.23, 1.0, 0.0)).norm() < 1e-9);
        // Towards `odom` only odom's chain leads: the same samples, every one of them (a mix would
        // have left each parent's edge only the samples since the other's last).
        let got = tf.lookup("odom", "camera", 0.0).unwrap();
        assert!(got.translation.vector.norm() < 1e-9);
        let got = tf.lookup("odom", "camera", 1.95).unwrap();
        assert!((got.translation.vector.x - 1.95).abs() < 1e-9);
        assert_eq!(tf.children("base_link"), vec!["camera".to_string()]);
    }

    #[test]
    fn a_loop_in_a_broken_recording_is_named_and_many_parents_stay_cheap() {
        // A loop (a -> b -> a, two nodes publishing the same pair both ways) and a ladder of frames
        // with two parents each (2^40 paths upwards, if the search walked every one).
        let mut tf = TfTree::default();
        tf.add("a", "b", 0.0, Isometry3::identity(), true);
        tf.add("b", "a", 0.0, Isometry3::identity(), true);
        tf.add("a", "camera", 0.0, Isometry3::identity(), true);
        for i in 0..40 {
            let (low, up) = (
                format!("l{i}"),
                [format!("l{}", i + 1), format!("r{}", i + 1)],
            );
            for parent in &up {
                tf.add(parent, &low, 0.0, Isometry3::identity(), true);
            }
            tf.add(&up[0], &format!("r{i}"), 0.0, Isometry3::identity(), true);
        }
        tf.seal();
        let e = tf.lookup("map", "camera", 0.0).unwrap_err();
        assert!(e.contains("loop") || e.contains("map"), "{e}");
        assert_eq!(tf.parent_towards("l0", "nowhere"), Some("l1"));
        assert!(tf.lookup("l40", "l0", 0.0).is_ok());
    }
}
