//! bgkmap: a 3D occupancy map built with exact Bayesian Generalized Kernel (BGK) inference.
//!
//! Layers, from the bottom up (each depends only on the ones before it):
//!
//! | module | owns | must not depend on |
//! |---|---|---|
//! | [`core`] | keys, blocks, the sparse kernel, scan → training data → evidence, queries, merge | I/O, async, network |
//! | [`io`] | file codecs: PCD, OctoMap `.bt`, PLY, CSV | the store, network |
//! | [`store`] | the on-disk map file (SQLite) | network |
//! | [`sim`] | a built-in scene and a simulated LiDAR with analytic ground truth | network |
//! | [`eval`] | ROC / AUC against a ground-truth map | network |
//! | [`service`] | named maps, one writer per map, snapshots for readers, dedup of scans | any transport or wire format |
//! | `cli` (binary only) | the `bgkmap` command line | — |
#![cfg_attr(test, allow(clippy::unwrap_used))]

#[cfg(feature = "server")]
pub mod api;
pub mod core;
pub mod eval;
pub mod io;
pub mod service;
pub mod sim;
pub mod store;

#[cfg(feature = "cli")]
pub mod cli;
