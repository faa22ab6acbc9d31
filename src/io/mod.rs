//! File and message codecs: PCD scans, OctoMap `.bt` trees, PLY and CSV exports, ROS 2 messages
//! (CDR).
//!
//! Codecs are pure functions over byte slices and writers; they know nothing about the store or
//! the network.

pub mod lzf;
pub mod octomap;
pub mod pcd;
pub mod ply;
pub mod ros2;
pub mod scan;
