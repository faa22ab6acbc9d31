//! The sensor pose at a cloud's stamp, as ROS does it: a history of stamped poses per edge,
//! interpolated between the two samples around the stamp (linear translation, slerp rotation),
//! and a tree of frames (`/tf`, `/tf_static`) walked from the sensor frame up to the world frame.
//!
//! A stamp that matches a sample exactly gets that sample unchanged (no rounding from the
//! interpolation), and a single edge is returned as stored: a cloud posed by a driver that stamps
//! pose and cloud alike lands exactly where the pose says.

use crate::core::Pose;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use std::collections::{HashMap, VecDeque};

/// Samples older than this (behind the newest) are forgotten: 10 s, as tf2's default cache.
pub const HISTORY_NS: i64 = 10_000_000_000;
/// Most samples kept per edge (a 1 kHz pose stream fills 10 s).
pub const MAX_SAMPLES: usize = 10_000;
/// Longest frame chain walked (a cycle in bad `/tf` data stops here).
const MAX_DEPTH: usize = 64;

/// The answer to "the pose at stamp t".
#[derive(Debug, Clone, PartialEq)]
pub enum Lookup {
    Ready(Pose),
    /// Not known yet: t is newer than the newest sample, or an edge has not arrived.
    Wait,
    /// Never answerable (t is older than the history kept); the reason.
    Never(String),
}

/// Stamped poses of one moving frame, sorted by stamp.
#[derive(Debug, Clone, Default)]
pub struct PoseHistory {
    samples: VecDeque<(i64, Pose)>,
}

impl PoseHistory {
    /// Adds a sample (a repeated stamp replaces the earlier one); forgets samples beyond
    /// [`HISTORY_NS`] or [`MAX_SAMPLES`]. Invalid poses are refused with the reason.
    pub fn insert(&mut self, stamp_ns: i64, pose: Pose) -> Result<(), String> {
        pose.validate().map_err(|e| e.to_string())?;
        let i = self.samples.partition_point(|(t, _)| *t < stamp_ns);
        match self.samples.get_mut(i) {
            Some(s) if s.0 == stamp_ns => s.1 = pose,
            _ => self.samples.insert(i, (stamp_ns, pose)),
        }
        let newest = self.samples.back().map_or(stamp_ns, |s| s.0);
        while self.samples.len() > MAX_SAMPLES
            || self.samples.front().is_some_and(|s| newest.saturating_sub(s.0) > HISTORY_NS)
        {
            self.samples.pop_front();
        }
        Ok(())
    }

    /// The pose at `stamp_ns`: exact sample, or interpolated between its neighbours.
    pub fn at(&self, stamp_ns: i64) -> Lookup {
        let (Some(first), Some(last)) = (self.samples.front(), self.samples.back()) else {
            return Lookup::Wait;
        };
        if stamp_ns > last.0 {
            return Lookup::Wait;
        }
        if stamp_ns < first.0 {
            return Lookup::Never(format!(
                "stamp {stamp_ns} ns is older than the oldest pose kept ({} ns)",
                first.0
            ));
        }
        let i = self.samples.partition_point(|(t, _)| *t < stamp_ns);
        let (t1, p1) = self.samples[i];
        if t1 == stamp_ns {
            return Lookup::Ready(p1);
        }
        let (t0, p0) = self.samples[i - 1];
        let s = (stamp_ns - t0) as f64 / (t1 - t0) as f64;
        Lookup::Ready(interpolate(&p0, &p1, s))
    }
}

fn rotation(p: &Pose) -> UnitQuaternion<f64> {
    let [w, x, y, z] = p.rotation_wxyz;
    UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
}

fn from_isometry(iso: &Isometry3<f64>) -> Pose {
    let t = iso.translation.vector;
    let q = iso.rotation.quaternion();
    Pose { translation_m: [t.x, t.y, t.z], rotation_wxyz: [q.w, q.i, q.j, q.k] }
}

fn isometry(p: &Pose) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::from(Vector3::from(p.translation_m)), rotation(p))
}

/// `p0` → `p1` at fraction `s`: translation linear, rotation by slerp (shortest arc).
fn interpolate(p0: &Pose, p1: &Pose, s: f64) -> Pose {
    let (a, b) = (Vector3::from(p0.translation_m), Vector3::from(p1.translation_m));
    let t = a + (b - a) * s;
    let (q0, q1) = (rotation(p0), rotation(p1));
    let q = q0.try_slerp(&q1, s, 1e-9).unwrap_or(q0);
    let q = q.quaternion();
    Pose { translation_m: [t.x, t.y, t.z], rotation_wxyz: [q.w, q.i, q.j, q.k] }
}

/// One edge of the tree: `parent_from_child`, static or over time.
#[derive(Debug, Clone)]
enum Edge {
    Static(Pose),
    Moving(PoseHistory),
}

/// The frame tree from `/tf` and `/tf_static`: per child frame, its parent and the transform.
#[derive(Debug, Clone, Default)]
pub struct TfTree {
    edges: HashMap<String, (String, Edge)>,
}

impl TfTree {
    /// Records `parent_from_child` at `stamp_ns` (static edges hold at every stamp). A child that
    /// changes parent keeps only the newest parent.
    pub fn insert(
        &mut self,
        parent: &str,
        child: &str,
        stamp_ns: i64,
        parent_from_child: Pose,
        is_static: bool,
    ) -> Result<(), String> {
        if parent == child || parent.is_empty() || child.is_empty() {
            return Err(format!("bad transform {parent:?} → {child:?}"));
        }
        if is_static {
            parent_from_child.validate().map_err(|e| e.to_string())?;
            self.edges.insert(child.to_string(), (parent.to_string(), Edge::Static(parent_from_child)));
            return Ok(());
        }
        let entry = self
            .edges
            .entry(child.to_string())
            .or_insert_with(|| (parent.to_string(), Edge::Moving(PoseHistory::default())));
        if entry.0 != parent || matches!(entry.1, Edge::Static(_)) {
            *entry = (parent.to_string(), Edge::Moving(PoseHistory::default()));
        }
        match &mut entry.1 {
            Edge::Moving(h) => h.insert(stamp_ns, parent_from_child),
            Edge::Static(_) => Ok(()),
        }
    }

    /// `world_from_frame` at `stamp_ns`, walking parents from `frame` up to `world`.
    pub fn lookup(&self, world: &str, frame: &str, stamp_ns: i64) -> Lookup {
        if frame == world {
            return Lookup::Ready(Pose::IDENTITY);
        }
        // Edges from `frame` upwards: child_from_grandchild… composed world-side last.
        let mut chain: Vec<Pose> = Vec::new();
        let mut at = frame;
        while at != world {
            if chain.len() == MAX_DEPTH {
                return Lookup::Never(format!("no chain of transforms {world:?} ← {frame:?} (cycle?)"));
            }
            let Some((parent, edge)) = self.edges.get(at) else { return Lookup::Wait };
            let pose = match edge {
                Edge::Static(p) => *p,
                Edge::Moving(h) => match h.at(stamp_ns) {
                    Lookup::Ready(p) => p,
                    Lookup::Never(why) => return Lookup::Never(format!("{parent:?} ← {at:?}: {why}")),
                    Lookup::Wait => return Lookup::Wait,
                },
            };
            chain.push(pose);
            at = parent;
        }
        let mut poses = chain.into_iter().rev();
        let Some(first) = poses.next() else { return Lookup::Ready(Pose::IDENTITY) };
        let mut rest = poses.peekable();
        if rest.peek().is_none() {
            return Lookup::Ready(first); // one edge: exactly as published
        }
        let world_from_frame = rest.fold(isometry(&first), |acc, p| acc * isometry(&p));
        Lookup::Ready(from_isometry(&world_from_frame))
    }
}

#[cfg(test)]
#[path = "tf_tests.rs"]
mod tests;
