//! `bgkmap check`, `bgkmap retract` and `bgkmap repose`: verify a map file, and change one in
//! place exactly (under the map's writer lock, so never behind a running server's back).

use super::args::parse_floats;
use crate::core::Pose;
use crate::store::check::check_map;
use crate::store::{DurableMap, ScanId, ScanSelector};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct CheckArgs {
    /// Map file.
    pub map: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// Verifies a map file; exits 1 when anything is damaged.
pub fn run_check(a: CheckArgs) -> Result<()> {
    let r = check_map(&a.map)?;
    if a.json {
        let blocks: Vec<_> = r
            .corrupt_blocks
            .iter()
            .map(|c| serde_json::json!({"block": [c.key.x, c.key.y, c.key.z], "reason": c.reason}))
            .collect();
        let records: Vec<_> = r
            .corrupt_records
            .iter()
            .map(|((s, q), why)| serde_json::json!({"source": s, "seq": q, "reason": why}))
            .collect();
        let out = serde_json::json!({"ok": r.is_ok(), "version": r.version, "blocks": r.blocks,
            "corrupt_blocks": blocks, "scans": r.scans, "record_bytes": r.record_bytes,
            "corrupt_records": records, "problems": r.problems});
        println!("{out}");
    } else {
        println!(
            "{}: map version {}, {} blocks, journal {:?}, {} bytes of raw scans",
            a.map.display(),
            r.version,
            r.blocks,
            r.scans,
            r.record_bytes
        );
        for c in &r.corrupt_blocks {
            println!("corrupt block ({}, {}, {}): {}", c.key.x, c.key.y, c.key.z, c.reason);
        }
        for ((s, q), why) in &r.corrupt_records {
            println!("corrupt journal record of scan ({s}, {q}): {why}");
        }
        for p in &r.problems {
            println!("problem: {p}");
        }
    }
    if !r.is_ok() {
        bail!(
            "{}: damaged ({} corrupt blocks, {} corrupt journal records, {} other problems)",
            a.map.display(),
            r.corrupt_blocks.len(),
            r.corrupt_records.len(),
            r.problems.len()
        );
    }
    println!("ok");
    Ok(())
}

/// `SOURCE:SEQ` (the source may itself contain `:`; the seq is after the last one).
fn parse_scan_id(s: &str) -> Result<ScanId, String> {
    let (source, seq) = s.rsplit_once(':').ok_or_else(|| format!("expected SOURCE:SEQ, got {s:?}"))?;
    let seq = seq.parse::<u64>().map_err(|_| format!("{seq:?} is not a sequence number"))?;
    if source.is_empty() {
        return Err(format!("empty source in {s:?}"));
    }
    Ok((source.to_string(), seq))
}

#[derive(Debug, Args)]
pub struct RetractArgs {
    /// Map file (changed in place).
    pub map: PathBuf,
    /// Retract these scans (SOURCE:SEQ, repeatable)…
    #[arg(long = "scan", value_parser = parse_scan_id, conflicts_with_all = ["source", "from_stamp", "to_stamp"])]
    pub scans: Vec<ScanId>,
    /// …or every scan of this source (optionally within the stamp range)…
    #[arg(long)]
    pub source: Option<String>,
    /// …with stamp ≥ FROM_STAMP (Unix ns)…
    #[arg(long, allow_negative_numbers = true)]
    pub from_stamp: Option<i64>,
    /// …and stamp < TO_STAMP (Unix ns).
    #[arg(long, allow_negative_numbers = true)]
    pub to_stamp: Option<i64>,
}

pub fn run_retract(a: RetractArgs) -> Result<()> {
    let selector = ScanSelector {
        scans: a.scans,
        source: a.source,
        from_stamp_nanos: a.from_stamp,
        to_stamp_nanos: a.to_stamp,
    };
    let mut map = DurableMap::open_recovered(&a.map)?;
    let change = map.retract(&selector).with_context(|| format!("{}: cannot retract", a.map.display()))?;
    map.close()?;
    eprintln!(
        "{}: {} scans retracted, {} blocks changed, map version {}",
        a.map.display(),
        change.scans,
        change.blocks_changed,
        change.version
    );
    Ok(())
}

/// `SOURCE:SEQ=TX,TY,TZ,QW,QX,QY,QZ`.
fn parse_scan_pose(s: &str) -> Result<(ScanId, Pose), String> {
    let (id, pose) =
        s.split_once('=').ok_or_else(|| format!("expected SOURCE:SEQ=TX,TY,TZ,QW,QX,QY,QZ, got {s:?}"))?;
    let v = parse_floats(pose, 7)?;
    Ok((
        parse_scan_id(id)?,
        Pose { translation_m: [v[0], v[1], v[2]], rotation_wxyz: [v[3], v[4], v[5], v[6]] },
    ))
}

#[derive(Debug, Args)]
pub struct ReposeArgs {
    /// Map file (changed in place).
    pub map: PathBuf,
    /// A corrected pose, SOURCE:SEQ=TX,TY,TZ,QW,QX,QY,QZ (metres; unit quaternion w, x, y, z).
    #[arg(long = "pose", value_parser = parse_scan_pose, allow_hyphen_values = true)]
    pub poses: Vec<(ScanId, Pose)>,
    /// A file of corrected poses, one `SOURCE:SEQ=TX,TY,TZ,QW,QX,QY,QZ` per line (`#` comments).
    #[arg(long)]
    pub poses_file: Option<PathBuf>,
}

pub fn run_repose(a: ReposeArgs) -> Result<()> {
    let mut poses = a.poses;
    if let Some(file) = &a.poses_file {
        let text =
            std::fs::read_to_string(file).with_context(|| format!("{}: cannot read", file.display()))?;
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            poses.push(
                parse_scan_pose(line).map_err(|e| anyhow::anyhow!("{}:{}: {e}", file.display(), i + 1))?,
            );
        }
    }
    if poses.is_empty() {
        bail!("no poses given (--pose or --poses-file)");
    }
    let mut map = DurableMap::open_recovered(&a.map)?;
    let change = map.repose(&poses).with_context(|| format!("{}: cannot re-pose", a.map.display()))?;
    map.close()?;
    eprintln!(
        "{}: {} scans re-posed, {} blocks changed, map version {}",
        a.map.display(),
        change.scans,
        change.blocks_changed,
        change.version
    );
    Ok(())
}
