//! `bgkmap build` and `bgkmap merge`.

use super::args::{ParamArgs, ScanArgs, load_raw_scan, load_scan, progress};
use crate::core::{EvidenceMap, Integrator};
use crate::store::{DurableMap, MapReader, NewScan, lock, now_nanos, save_map_with_scans, temp_sibling};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct BuildArgs {
    /// Output map file (replaced atomically when the build succeeds).
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub params: ParamArgs,
    #[command(flatten)]
    pub scan: ScanArgs,
    /// Threads per scan (results are bit-identical for any count).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Journal the scans as (SOURCE, FIRST_SEQ + i) with their raw points, so the map can be
    /// merged exactly with maps sharing scans, and scans retracted or re-posed. Without it the
    /// map holds evidence only.
    #[arg(long)]
    pub source: Option<String>,
    /// Sequence number of the first scan (with --source).
    #[arg(long, default_value_t = 1, requires = "source")]
    pub first_seq: u64,
    /// PCD scans, integrated in the order given.
    #[arg(required = true)]
    pub scans: Vec<PathBuf>,
}

pub fn run_build(a: BuildArgs) -> Result<()> {
    let params = a.params.to_params()?;
    let mut map = EvidenceMap::new(params);
    let mut integrator = Integrator::new(params);
    let bar = progress(a.scans.len() as u64, "build");
    let mut dropped = 0;
    let mut journal = Vec::new();
    for (i, path) in a.scans.iter().enumerate() {
        match &a.source {
            None => {
                let scan = load_scan(path, &a.scan)?;
                dropped += scan.dropped_nonfinite;
                integrator.integrate(&mut map, &scan.points_world, scan.origin_world, a.threads.max(1));
            }
            Some(source) => {
                let (raw, n_dropped) = load_raw_scan(path, &a.scan)?;
                dropped += n_dropped;
                raw.add_into(&mut integrator, &mut map, a.threads.max(1))
                    .with_context(|| format!("{}", path.display()))?;
                let seq = a.first_seq + i as u64;
                let now = now_nanos();
                journal.push(NewScan {
                    source: source.clone(),
                    seq,
                    stamp_nanos: now,
                    received_nanos: now,
                    scan: raw,
                });
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    save_map_with_scans(&a.out, &map, &journal, a.scans.len() as u64)?;
    eprintln!(
        "{}: {} scans{}, {} blocks, {} cells with evidence, {} non-finite points dropped",
        a.out.display(),
        a.scans.len(),
        if journal.is_empty() { "" } else { " (journaled)" },
        map.block_count(),
        map.cells_with_evidence(),
        dropped
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct MergeArgs {
    /// Map files to merge (at least two).
    #[arg(required = true, num_args = 2..)]
    pub maps: Vec<PathBuf>,
    /// Output map file.
    #[arg(long)]
    pub out: PathBuf,
}

/// Removes a temporary map file and its SQLite and lock siblings.
fn remove_temp(tmp: &Path) {
    let _ = std::fs::remove_file(tmp);
    for suffix in ["-wal", "-shm", "-journal"] {
        let mut name = tmp.as_os_str().to_os_string();
        name.push(suffix);
        let _ = std::fs::remove_file(PathBuf::from(name));
    }
    let _ = std::fs::remove_file(lock::lock_path(tmp));
}

/// The exact sum of several maps: a copy of the first, then each other merged in (scans that
/// both hold are counted once; see `DurableMap::merge_from`).
pub fn run_merge(a: MergeArgs) -> Result<()> {
    let Some((first, rest)) = a.maps.split_first() else { bail!("merge needs at least two maps") };
    let tmp = temp_sibling(&a.out);
    remove_temp(&tmp);
    let result = (|| -> Result<(u64, usize, usize)> {
        MapReader::open(first)?.copy_to(&tmp)?;
        let mut merged = DurableMap::open_recovered(&tmp)?;
        let mut shared = 0;
        for path in rest {
            let change = merged
                .merge_from(path)
                .with_context(|| format!("cannot merge {} into {}", path.display(), first.display()))?;
            shared += change.shared;
        }
        let (blocks, cells) = (merged.map().block_count(), merged.map().cells_with_evidence());
        merged.close()?;
        Ok((shared, blocks, cells))
    })();
    let (shared, blocks, cells) = match result {
        Ok(r) => r,
        Err(e) => {
            remove_temp(&tmp);
            return Err(e);
        }
    };
    let renamed = std::fs::rename(&tmp, &a.out);
    remove_temp(&tmp);
    renamed.with_context(|| format!("{}: cannot write", a.out.display()))?;
    eprintln!(
        "{}: {blocks} blocks, {cells} cells with evidence, {shared} shared scans counted once",
        a.out.display()
    );
    Ok(())
}
