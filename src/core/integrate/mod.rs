//! The integration pipeline: one scan → training data → kernel sums → evidence added to the map.
//!
//! It reads and writes the data model (`key`, `params`, the posterior's fixed point, blocks and
//! the map); nothing in the model imports from here.
pub mod cell_points;
pub mod delta;
pub mod edit;
pub mod floor;
mod free_space;
pub mod integrator;
pub mod kernel;
pub mod raw_scan;
pub mod scatter;
pub mod simd;
pub mod sink;
pub mod training;
mod voxel_table;
pub mod window;
pub mod workers;

#[cfg(test)]
mod evidence_tests;
