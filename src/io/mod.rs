//! File codecs: PCD scans, OctoMap `.bt` trees, PLY and CSV exports.
//!
//! Codecs are pure functions over byte slices and writers; they know nothing about the store or
//! the network.

pub mod lzf;
pub mod octomap;
pub mod pcd;
pub mod ply;
pub mod scan;
