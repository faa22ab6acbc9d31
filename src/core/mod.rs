//! The pure, synchronous BGK core, in two layers.
//!
//! - **The data model** — [`key`], [`params`], [`pose`]; [`posterior`] (a cell's evidence, its
//!   Beta posterior and the fixed-point unit); [`block`] (block storage); [`block_table`] and
//!   [`map`] (the evidence map); [`prefetch`]; and [`query`] (point, box and ray queries, which
//!   read the model only). Nothing in the model imports from the pipeline.
//! - **The integration pipeline** — [`integrate`]: scan → training data → kernel sums →
//!   evidence added to the map, on one thread or on [`integrate::workers`]' threads.
//!
//! Nothing here does I/O, spawns tasks or knows about a network transport; the only threads are
//! the workers', for ingest on several cores. Evidence is integer fixed point (see
//! [`posterior`]), so every way of combining the same scans gives the same bits.

pub mod block;
pub mod block_table;
pub mod integrate;
pub mod key;
pub mod map;
pub mod params;
pub mod pose;
pub mod posterior;
pub mod prefetch;
pub mod query;

pub use integrate::edit::{EditedBlocks, MapEdit};
pub use integrate::integrator::Integrator;
pub use integrate::raw_scan::RawScan;
pub use integrate::sink::BlockSink;
pub use integrate::workers::{Workers, integrate_parallel};
pub use key::{BlockKey, CellKey};
pub use map::EvidenceMap;
pub use params::{MapParams, RangeMode, Thresholds};
pub use pose::{PointFrame, Pose};
pub use posterior::{CellEstimate, CellState};
