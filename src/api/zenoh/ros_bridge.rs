//! What the ROS 2 bridge does with each message, free of zenoh: decode (`crate::io::ros2`),
//! pair every cloud with the sensor pose at its stamp, and turn it into a scan.
//!
//! - **Identity** of a scan: source = the configured name (default the topic), seq = the
//!   cloud's `header.stamp` in nanoseconds since the epoch. Stamps identify a measurement across
//!   retries, publisher restarts and replays of the same bag, so exactly-once holds end to end
//!   (rmw_zenoh's attachment sequence number restarts at 1 with every publisher and would not).
//!   A cloud stamped 0 cannot be identified and is refused. The stamp is also the scan's
//!   `stamp_nanos` in the journal (retraction by time range).
//! - **Pose**: `identity`; the pose topic interpolated at the stamp; or the `/tf` chain from the
//!   world frame to the cloud's frame. A cloud newer than every pose waits (at most
//!   [`MAX_PENDING`] clouds, oldest refused first) until a pose at or after its stamp arrives.
//! - **Frames**: a cloud in the world frame (or with an empty `frame_id`) is used as it is and
//!   the pose gives only the ray origin (of `sensor_frame` with `tf`); any other cloud is in the
//!   sensor frame and moved by the pose. A leading `/` (ROS 1 style, `/map`) is ignored in
//!   every frame name.
//! - Non-finite points go to the service, which drops and counts them per source.

use super::config::{RosPose, RosTopicConfig};
use crate::core::{PointFrame, Pose};
use crate::io::ros2::tf::{Lookup, PoseHistory, TfTree};
use crate::io::ros2::{PointCloud2, PoseStamped, decode_tf_message};
use crate::service::ScanInput;
use std::collections::VecDeque;

/// Clouds waiting for their pose.
pub const MAX_PENDING: usize = 16;

/// A message from one of the bridge's subscriptions.
#[derive(Debug, Clone, PartialEq)]
pub enum Incoming {
    Cloud(Vec<u8>),
    Pose(Vec<u8>),
    Tf { payload: Vec<u8>, is_static: bool },
}

/// What to do after a message.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Submit this scan.
    Scan(ScanInput),
    /// A cloud refused: count it as rejected for the source and log once.
    Reject { kind: &'static str, reason: String },
    /// A pose or transform refused: log once (not a scan, not counted).
    Fault { kind: &'static str, reason: String },
}

#[derive(Debug)]
struct PendingCloud {
    stamp_ns: i64,
    frame_id: String,
    points: Vec<[f32; 3]>,
}

/// The state of one configured topic.
#[derive(Debug)]
pub struct RosBridge {
    source: String,
    pose: RosPose,
    world_frame: String,
    sensor_frame: Option<String>,
    poses: PoseHistory,
    tf: TfTree,
    pending: VecDeque<PendingCloud>,
}

/// A frame name without the ROS 1 leading `/`.
fn frame(name: &str) -> &str {
    name.strip_prefix('/').unwrap_or(name)
}

fn reject(kind: &'static str, reason: impl Into<String>) -> Outcome {
    Outcome::Reject { kind, reason: reason.into() }
}

impl RosBridge {
    pub fn new(cfg: &RosTopicConfig) -> Self {
        Self {
            source: cfg.source_name().to_string(),
            pose: cfg.pose,
            world_frame: frame(&cfg.world_frame).to_string(),
            sensor_frame: cfg.sensor_frame.as_deref().map(|f| frame(f).to_string()),
            poses: PoseHistory::default(),
            tf: TfTree::default(),
            pending: VecDeque::new(),
        }
    }

    /// Takes one message; returns what became of it and of the clouds it released.
    pub fn handle(&mut self, msg: Incoming) -> Vec<Outcome> {
        let mut out = Vec::new();
        match msg {
            Incoming::Cloud(payload) => self.on_cloud(&payload, &mut out),
            Incoming::Pose(payload) => self.on_pose(&payload, &mut out),
            Incoming::Tf { payload, is_static } => self.on_tf(&payload, is_static, &mut out),
        }
        self.release(&mut out);
        out
    }

    /// At shutdown: the clouds still waiting for a pose are refused.
    pub fn finish(&mut self) -> Vec<Outcome> {
        self.pending
            .drain(..)
            .map(|c| {
                reject("no pose", format!("cloud stamped {} ns still had no pose at shutdown", c.stamp_ns))
            })
            .collect()
    }

    fn on_cloud(&mut self, payload: &[u8], out: &mut Vec<Outcome>) {
        let cloud = match PointCloud2::decode(payload) {
            Ok(c) => c,
            Err(e) => return out.push(reject("cdr", format!("sensor_msgs/PointCloud2: {e}"))),
        };
        let points = match cloud.points_xyz() {
            Ok(p) => p,
            Err(e) => return out.push(reject("point fields", e.to_string())),
        };
        if cloud.header.stamp_ns <= 0 {
            let reason = "header.stamp must be after the epoch: it is the scan's sequence number";
            return out.push(reject("stamp", reason));
        }
        if self.pending.len() == MAX_PENDING
            && let Some(old) = self.pending.pop_front()
        {
            let reason = format!(
                "no pose for the cloud stamped {} ns before {MAX_PENDING} newer clouds",
                old.stamp_ns
            );
            out.push(reject("no pose", reason));
        }
        let frame_id = frame(cloud.header.frame_id).to_string();
        self.pending.push_back(PendingCloud { stamp_ns: cloud.header.stamp_ns, frame_id, points });
    }

    fn on_pose(&mut self, payload: &[u8], out: &mut Vec<Outcome>) {
        let fault = |reason: String| Outcome::Fault { kind: "pose", reason };
        let p = match PoseStamped::decode(payload) {
            Ok(p) => p,
            Err(e) => return out.push(fault(format!("geometry_msgs/PoseStamped: {e}"))),
        };
        let pose_frame = frame(p.header.frame_id);
        if !pose_frame.is_empty() && pose_frame != self.world_frame {
            return out.push(fault(format!("pose in frame {pose_frame:?}, expected {:?}", self.world_frame)));
        }
        if let Err(e) = self.poses.insert(p.header.stamp_ns, p.pose) {
            out.push(fault(e));
        }
    }

    fn on_tf(&mut self, payload: &[u8], is_static: bool, out: &mut Vec<Outcome>) {
        let fault = |reason: String| Outcome::Fault { kind: "tf", reason };
        match decode_tf_message(payload) {
            Err(e) => out.push(fault(format!("tf2_msgs/TFMessage: {e}"))),
            Ok(transforms) => {
                for t in transforms {
                    let (parent, child) = (frame(t.header.frame_id), frame(t.child_frame_id));
                    if let Err(e) =
                        self.tf.insert(parent, child, t.header.stamp_ns, t.parent_from_child, is_static)
                    {
                        out.push(fault(e));
                    }
                }
            }
        }
    }

    /// The pose of `frame` in the world at `stamp_ns`.
    fn pose_at(&self, frame: &str, stamp_ns: i64) -> Lookup {
        match self.pose {
            RosPose::Identity => Lookup::Ready(Pose::IDENTITY),
            RosPose::Topic => self.poses.at(stamp_ns),
            RosPose::Tf => self.tf.lookup(&self.world_frame, frame, stamp_ns),
        }
    }

    /// Turns every waiting cloud whose pose is known into a scan (or a refusal).
    fn release(&mut self, out: &mut Vec<Outcome>) {
        let mut waiting = VecDeque::with_capacity(self.pending.len());
        while let Some(c) = self.pending.pop_front() {
            let in_world = c.frame_id.is_empty() || c.frame_id == self.world_frame;
            let pose_frame = match (in_world, &self.sensor_frame) {
                (true, Some(sensor)) => sensor.as_str(),
                (true, None) => self.world_frame.as_str(),
                (false, _) => c.frame_id.as_str(),
            };
            match self.pose_at(pose_frame, c.stamp_ns) {
                Lookup::Wait => waiting.push_back(c),
                Lookup::Never(why) => out.push(reject("no pose", why)),
                Lookup::Ready(world_from_sensor) => out.push(Outcome::Scan(ScanInput {
                    source: self.source.clone(),
                    seq: c.stamp_ns as u64,
                    world_from_sensor,
                    frame: if in_world { PointFrame::World } else { PointFrame::Sensor },
                    points: c.points,
                    max_range_m: None,
                    stamp_nanos: Some(c.stamp_ns),
                })),
            }
        }
        self.pending = waiting;
    }
}

#[cfg(test)]
#[path = "ros_bridge_tests.rs"]
mod tests;
