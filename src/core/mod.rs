//! The pure, synchronous BGK core: keys and blocks, the sparse kernel, scan → training data →
//! evidence, the evidence map, and point / box / ray queries.
//!
//! Nothing here does I/O, spawns tasks or knows about a network transport; the only threads are
//! [`pool`]'s, for ingest on several cores. Evidence is integer fixed-point (see [`evidence`]),
//! so every way of combining the same scans gives the same bits.

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
