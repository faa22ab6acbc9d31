//! `bgkmap build` and `bgkmap merge`.

use super::args::{ParamArgs, ScanArgs, load_scan, progress};
use crate::core::{EvidenceMap, Integrator};
use crate::store::{load_map, save_map};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;

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
    for path in &a.scans {
        let scan = load_scan(path, &a.scan)?;
        dropped += scan.dropped_nonfinite;
        integrator.integrate(&mut map, &scan.points_world, scan.origin_world, a.threads.max(1));
        bar.inc(1);
    }
    bar.finish_and_clear();
    save_map(&a.out, &map)?;
    eprintln!(
        "{}: {} scans, {} blocks, {} cells with evidence, {} non-finite points dropped",
        a.out.display(),
        a.scans.len(),
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

pub fn run_merge(a: MergeArgs) -> Result<()> {
    let mut iter = a.maps.iter();
    let Some(first) = iter.next() else { bail!("merge needs at least two maps") };
    let mut merged = load_map(first)?;
    for path in iter {
        let other = load_map(path)?;
        if let Err(diff) = merged.merge_from(&other) {
            bail!(
                "cannot merge {} into {}: map parameters differ ({})",
                path.display(),
                first.display(),
                diff.join("; ")
            );
        }
    }
    save_map(&a.out, &merged).with_context(|| "writing the merged map")?;
    eprintln!(
        "{}: {} blocks, {} cells with evidence",
        a.out.display(),
        merged.block_count(),
        merged.cells_with_evidence()
    );
    Ok(())
}
