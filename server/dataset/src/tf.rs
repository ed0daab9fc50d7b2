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

/// The transforms of a recording.
#[derive(Default)]
pub struct TfTree {
    /// child -> (parent, edge); a frame has one parent.
    edges: HashMap<String, (String, Edge)>,
    /// Dynamic edges as trajectories, built by [`TfTree::seal`].
    sealed: HashMap<String, Trajectory>,
}

impl TfTree {
    /// Add `parent_from_child` at `stamp` seconds (`is_static`: from `/tf_static`, valid at any time).
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
        if is_static {
            self.edges
                .insert(child, (parent, Edge::Static(parent_from_child)));
            return;
        }
        match self.edges.get_mut(&child) {
            Some((p, Edge::Dynamic(v))) if *p == parent => v.push((stamp, parent_from_child)),
            Some((_, Edge::Static(_))) => {}
            _ => {
                self.edges.insert(
                    child,
                    (parent, Edge::Dynamic(vec![(stamp, parent_from_child)])),
                );
            }
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
        self.sealed = self
            .edges
            .iter_mut()
            .filter_map(|(child, (_, e))| match e {
                Edge::Dynamic(v) => {
                    Some((child.clone(), Trajectory::from_poses(std::mem::take(v))))
                }
                Edge::Static(_) => None,
            })
            .collect();
    }

    /// `root_from_frame` at `t` and the root's name, or why not.
    fn to_root(&self, frame: &str, t: f64) -> Result<(Isometry3<f64>, String), String> {
        let mut pose = Isometry3::identity();
        let mut at = frame.to_string();
        for _ in 0..64 {
            let Some((parent, edge)) = self.edges.get(&at) else {
                return Ok((pose, at));
            };
            let hop = match edge {
                Edge::Static(p) => *p,
                Edge::Dynamic(_) => {
                    let traj = self.sealed.get(&at).ok_or("the TF tree is not sealed")?;
                    traj.at_within(t, TF_MAX_GAP_S).ok_or_else(|| {
                        let (a, b) = traj.span().unwrap_or((f64::NAN, f64::NAN));
                        format!(
                            "no transform {parent} -> {at} at {t:.6} s (recorded from {a:.6} to {b:.6} s, or a gap of more than {TF_MAX_GAP_S} s)"
                        )
                    })?
                }
            };
            pose = hop * pose;
            at = parent.clone();
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
        let known =
            |f: &str| self.edges.contains_key(f) || self.edges.values().any(|(p, _)| p == f);
        for f in [target, source] {
            if !known(f) {
                return Err(format!(
                    "no transform from {target} to {source} at {t:.6} s: the TF tree has no frame {f} (frames: {})",
                    self.frames().join(", ")
                ));
            }
        }
        let (root_from_source, r1) = self
            .to_root(source, t)
            .map_err(|e| format!("no transform from {target} to {source} at {t:.6} s: {e}"))?;
        let (root_from_target, r2) = self
            .to_root(target, t)
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
            .flat_map(|(c, (p, _))| [c.clone(), p.clone()])
            .collect();
        v.sort();
        v.dedup();
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
}
