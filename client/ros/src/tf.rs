//! A transform buffer as tf2 keeps one: each child frame has one parent, a time-ordered history of
//! `parent_from_child` (from `/tf`, kept for `CACHE_NS`) or one static transform (from
//! `/tf_static`, valid at every time); a lookup walks both frames up to their common root and
//! interpolates each hop at the stamp (translation linearly, rotation by slerp), and fails rather
//! than extrapolate, as tf2's `lookupTransform` does.

use std::collections::{BTreeMap, HashMap};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::msgs;

/// How long `/tf` samples are kept (tf2's default cache: 10 s).
pub const CACHE_NS: i64 = 10_000_000_000;

/// A transform message's pose as an isometry (the quaternion normalized, as tf2 does).
pub fn isometry(t: &msgs::Transform) -> Isometry3<f64> {
    let q = t.rotation;
    Isometry3::from_parts(
        Translation3::new(t.translation.x, t.translation.y, t.translation.z),
        UnitQuaternion::from_quaternion(Quaternion::new(q.w, q.x, q.y, q.z)),
    )
}

/// An isometry as a transform message.
pub fn transform(p: &Isometry3<f64>) -> msgs::Transform {
    let q = p.rotation.quaternion();
    msgs::Transform {
        translation: msgs::Vector3 {
            x: p.translation.x,
            y: p.translation.y,
            z: p.translation.z,
        },
        rotation: msgs::Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    }
}

/// Why a lookup failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LookupError {
    /// A frame no transform names.
    #[error("frame {frame:?} does not exist (frames known: {known})")]
    UnknownFrame {
        /// The frame asked for.
        frame: String,
        /// The frames the buffer holds, comma-separated.
        known: String,
    },
    /// The two frames are in trees that do not connect.
    #[error(
        "{from:?} and {to:?} are not connected (their roots are {from_root:?} and {to_root:?})"
    )]
    NotConnected {
        /// Source frame.
        from: String,
        /// Target frame.
        to: String,
        /// The root above `from`.
        from_root: String,
        /// The root above `to`.
        to_root: String,
    },
    /// The stamp lies outside the history of one hop.
    #[error("{parent} -> {child} at {stamp:.3} s would need extrapolation (known from {first:.3} to {last:.3} s)")]
    Extrapolation {
        /// Parent of the hop.
        parent: String,
        /// Child of the hop.
        child: String,
        /// The stamp asked for, seconds.
        stamp: f64,
        /// The oldest sample kept, seconds.
        first: f64,
        /// The newest sample, seconds.
        last: f64,
    },
}

#[derive(Debug, Default)]
struct Edge {
    parent: String,
    /// `Some` for a static transform.
    fixed: Option<Isometry3<f64>>,
    /// Stamp (ns) -> parent_from_child.
    history: BTreeMap<i64, Isometry3<f64>>,
}

/// The transform tree.
#[derive(Debug, Default)]
pub struct Buffer {
    edges: HashMap<String, Edge>,
}

impl Buffer {
    /// Add the transforms of one message (`fixed`: from `/tf_static`). A child that gets another
    /// parent drops its history (the newest parent wins, as in tf2).
    pub fn add(&mut self, message: &msgs::TfMessage, fixed: bool) {
        for t in &message.transforms {
            let child = t.child_frame_id.trim_start_matches('/').to_string();
            let parent = t.header.frame_id.trim_start_matches('/').to_string();
            if child.is_empty() || parent.is_empty() || child == parent {
                continue;
            }
            let pose = isometry(&t.transform);
            if !pose.translation.vector.iter().all(|v| v.is_finite())
                || !pose.rotation.coords.iter().all(|v| v.is_finite())
            {
                continue;
            }
            let edge = self.edges.entry(child).or_default();
            if edge.parent != parent {
                edge.parent = parent;
                edge.history.clear();
                edge.fixed = None;
            }
            if fixed {
                edge.fixed = Some(pose);
                edge.history.clear();
            } else {
                let stamp = t.header.stamp.nanos();
                edge.fixed = None;
                edge.history.insert(stamp, pose);
                let newest = *edge.history.keys().next_back().unwrap_or(&stamp);
                edge.history = edge.history.split_off(&(newest - CACHE_NS));
            }
        }
    }

    /// The frames known (children and parents), sorted.
    pub fn frames(&self) -> Vec<String> {
        let mut all: Vec<String> = self
            .edges
            .iter()
            .flat_map(|(c, e)| [c.clone(), e.parent.clone()])
            .collect();
        all.sort();
        all.dedup();
        all
    }

    fn hop(&self, child: &str, stamp: i64) -> Result<(String, Isometry3<f64>), LookupError> {
        let e = &self.edges[child];
        if let Some(p) = e.fixed {
            return Ok((e.parent.clone(), p));
        }
        let extrapolation = || LookupError::Extrapolation {
            parent: e.parent.clone(),
            child: child.to_string(),
            stamp: stamp as f64 * 1e-9,
            first: e.history.keys().next().map_or(0, |s| *s) as f64 * 1e-9,
            last: e.history.keys().next_back().map_or(0, |s| *s) as f64 * 1e-9,
        };
        let after = e.history.range(stamp..).next();
        let before = e.history.range(..=stamp).next_back();
        let pose = match (before, after) {
            (Some((t0, p0)), Some((t1, p1))) => {
                if t1 == t0 {
                    *p0
                } else {
                    p0.lerp_slerp(p1, (stamp - t0) as f64 / (t1 - t0) as f64)
                }
            }
            _ => return Err(extrapolation()),
        };
        Ok((e.parent.clone(), pose))
    }

    /// `frame` and its ancestors up to its root, nearest first (the tree's structure only: no
    /// transform is evaluated).
    fn ancestors(&self, frame: &str) -> Vec<String> {
        let mut chain = vec![frame.to_string()];
        // A tree deeper than the number of edges has a cycle: stop there.
        for _ in 0..=self.edges.len() {
            let Some(e) = self.edges.get(chain.last().expect("not empty")) else {
                break;
            };
            chain.push(e.parent.clone());
        }
        chain
    }

    /// `ancestor_from_frame` at `stamp`, hopping from `frame` up to `ancestor` (one of its
    /// [`Buffer::ancestors`]); only the edges on that path are evaluated.
    fn up_to(
        &self,
        frame: &str,
        ancestor: &str,
        stamp: i64,
    ) -> Result<Isometry3<f64>, LookupError> {
        let mut at = frame.to_string();
        let mut ancestor_from_frame = Isometry3::identity();
        for _ in 0..=self.edges.len() {
            if at == ancestor || !self.edges.contains_key(&at) {
                break;
            }
            let (parent, parent_from_child) = self.hop(&at, stamp)?;
            ancestor_from_frame = parent_from_child * ancestor_from_frame;
            at = parent;
        }
        Ok(ancestor_from_frame)
    }

    /// `target_from_source` at `stamp` (ns): maps points of `source` into `target`. As tf2 does,
    /// the chain goes up from both frames only to their nearest common ancestor: `odom ->
    /// base_link` needs no `map -> odom` (beside robot_localization, whose `map -> odom` may
    /// pause, a lookup through the root would fail while odometry itself is fine).
    pub fn lookup(
        &self,
        target: &str,
        source: &str,
        stamp: i64,
    ) -> Result<Isometry3<f64>, LookupError> {
        let (target, source) = (
            target.trim_start_matches('/'),
            source.trim_start_matches('/'),
        );
        let known = self.frames();
        for f in [target, source] {
            if !known.iter().any(|k| k == f) {
                return Err(LookupError::UnknownFrame {
                    frame: f.to_string(),
                    known: known.join(", "),
                });
            }
        }
        let (up_t, up_s) = (self.ancestors(target), self.ancestors(source));
        let Some(common) = up_s.iter().find(|f| up_t.contains(f)) else {
            return Err(LookupError::NotConnected {
                from: source.to_string(),
                to: target.to_string(),
                from_root: up_s.last().cloned().unwrap_or_default(),
                to_root: up_t.last().cloned().unwrap_or_default(),
            });
        };
        let common_from_target = self.up_to(target, common, stamp)?;
        let common_from_source = self.up_to(source, common, stamp)?;
        Ok(common_from_target.inverse() * common_from_source)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn stamped(parent: &str, child: &str, ns: i64, p: Isometry3<f64>) -> msgs::TransformStamped {
        msgs::TransformStamped {
            header: msgs::Header {
                stamp: msgs::Time::from_nanos(ns),
                frame_id: parent.into(),
            },
            child_frame_id: child.into(),
            transform: transform(&p),
        }
    }

    #[test]
    fn chains_interpolate_and_refuse_to_extrapolate() {
        let mut b = Buffer::default();
        let cam = Isometry3::new(Vector3::new(0.1, 0.0, 0.3), Vector3::new(0.0, 0.0, 0.2));
        b.add(
            &msgs::TfMessage {
                transforms: vec![stamped("base_link", "camera", 0, cam)],
            },
            true,
        );
        let a = Isometry3::new(Vector3::new(0.0, 0.0, 0.0), Vector3::zeros());
        let c = Isometry3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.4));
        for (ns, p) in [(1_000_000_000, a), (2_000_000_000, c)] {
            b.add(
                &msgs::TfMessage {
                    transforms: vec![stamped("/odom", "base_link", ns, p)],
                },
                false,
            );
        }
        let got = b.lookup("odom", "camera", 1_500_000_000).unwrap();
        let want = Isometry3::new(Vector3::new(0.5, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.2)) * cam;
        assert!((got.translation.vector - want.translation.vector).norm() < 1e-9);
        assert!(got.rotation.angle_to(&want.rotation) < 1e-9);
        // The inverse direction.
        let back = b.lookup("camera", "odom", 1_500_000_000).unwrap();
        assert!((back * got).translation.vector.norm() < 1e-9);
        // Outside the history: refused, naming the hop and its range.
        let e = b.lookup("odom", "camera", 2_500_000_000).unwrap_err();
        assert!(e.to_string().contains("odom -> base_link"), "{e}");
        assert!(matches!(
            b.lookup("map", "camera", 1_500_000_000),
            Err(LookupError::UnknownFrame { .. })
        ));
    }

    #[test]
    fn a_lookup_goes_up_only_to_the_common_ancestor() {
        // robot_localization's map -> odom known only until 1 s (it paused); odometry goes on.
        let mut b = Buffer::default();
        let moving = |x: f64| Isometry3::new(Vector3::new(x, 0.0, 0.0), Vector3::zeros());
        for (ns, x) in [(0, 0.0), (1_000_000_000, 0.1)] {
            b.add(
                &msgs::TfMessage {
                    transforms: vec![stamped("map", "odom", ns, moving(x))],
                },
                false,
            );
        }
        for (ns, x) in [(4_000_000_000, 2.0), (6_000_000_000, 3.0)] {
            b.add(
                &msgs::TfMessage {
                    transforms: vec![stamped("odom", "base_link", ns, moving(x))],
                },
                false,
            );
        }
        let odom_from_base = b.lookup("odom", "base_link", 5_000_000_000).unwrap();
        assert!((odom_from_base.translation.vector.x - 2.5).abs() < 1e-9);
        // Through the paused edge, the lookup still fails, naming it.
        let e = b.lookup("map", "base_link", 5_000_000_000).unwrap_err();
        assert!(e.to_string().contains("map -> odom"), "{e}");
        // Two trees are not connected.
        b.add(
            &msgs::TfMessage {
                transforms: vec![stamped("elsewhere", "thing", 0, moving(0.0))],
            },
            true,
        );
        assert!(matches!(
            b.lookup("odom", "thing", 5_000_000_000),
            Err(LookupError::NotConnected { .. })
        ));
    }
}
