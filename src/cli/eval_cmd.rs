//! `bgkmap eval`: ROC / AUC of a map against a ground-truth `.bt` (docs/algorithm.md §10).

use super::plot::{RocCurve, write_roc_png};
use crate::core::EvidenceMap;
use crate::eval::{Roc, roc};
use crate::io::octomap::{BtTree, read_bt};
use crate::store::load_map;
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Map file(s); several maps are drawn on one ROC plot.
    #[arg(required = true)]
    pub maps: Vec<PathBuf>,
    /// Ground truth: an OctoMap .bt at the map's resolution.
    #[arg(long)]
    pub truth: PathBuf,
    /// Print one JSON object (an array for several maps).
    #[arg(long)]
    pub json: bool,
    /// Draw the ROC curve(s) to this PNG.
    #[arg(long)]
    pub roc: Option<PathBuf>,
}

/// The figures of one evaluation.
#[derive(Debug)]
pub struct EvalReport {
    pub map: String,
    /// Every truth cell a query; cells without evidence score 0.5.
    pub all: Roc,
    /// Only truth cells that hold evidence in the map.
    pub covered: Roc,
    pub queries: usize,
    pub covered_cells: usize,
}

impl EvalReport {
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "map": self.map,
            "auc": self.all.auc,
            "auc_covered": self.covered.auc,
            "queries": self.queries,
            "occupied": self.all.positives,
            "free": self.all.negatives,
            "covered_cells": self.covered_cells,
            "covered_definition": "truth cells with evidence in the map",
            "unknown_score": 0.5,
        })
    }
}

pub fn read_truth(path: &Path) -> Result<BtTree> {
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    read_bt(&bytes).with_context(|| format!("{}", path.display()))
}

/// Scores every truth cell with the map's probability (0.5 without evidence).
pub fn evaluate(name: &str, map: &EvidenceMap, truth: &BtTree) -> Result<EvalReport> {
    let res = map.params().resolution_m;
    if (truth.resolution - res).abs() > 1e-9 * res {
        bail!("truth resolution {} differs from the map's {}", truth.resolution, res);
    }
    let th = map.params().thresholds;
    let mut all = Vec::new();
    let mut covered = Vec::new();
    for (cell, occupied) in truth.cells() {
        let e = map.estimate(cell, &th);
        if e.evidence.is_empty() {
            all.push((0.5, occupied));
        } else {
            all.push((e.probability, occupied));
            covered.push((e.probability, occupied));
        }
    }
    let (queries, covered_cells) = (all.len(), covered.len());
    Ok(EvalReport {
        map: name.to_string(),
        all: roc(&mut all).context("AUC over all truth cells")?,
        covered: roc(&mut covered).context("AUC over covered cells")?,
        queries,
        covered_cells,
    })
}

pub fn run(a: EvalArgs) -> Result<()> {
    let truth = read_truth(&a.truth)?;
    let mut reports = Vec::new();
    for path in &a.maps {
        let map = load_map(path)?;
        reports.push(evaluate(&path.display().to_string(), &map, &truth)?);
    }
    if a.json {
        let v: Vec<_> = reports.iter().map(EvalReport::to_json).collect();
        let out = if v.len() == 1 { v[0].clone() } else { serde_json::Value::Array(v) };
        println!("{out}");
    } else {
        for r in &reports {
            println!(
                "{}: AUC {:.4} (unknown = 0.5, {} truth cells: {} occupied, {} free); covered-only AUC {:.4} ({} cells with evidence)",
                r.map, r.all.auc, r.queries, r.all.positives, r.all.negatives, r.covered.auc, r.covered_cells
            );
        }
    }
    if let Some(png) = &a.roc {
        let curves: Vec<_> =
            reports.iter().map(|r| RocCurve { label: file_label(&r.map), roc: &r.all }).collect();
        write_roc_png(png, &format!("ROC against {}", file_label(&a.truth.display().to_string())), &curves)?;
    }
    Ok(())
}

fn file_label(path: &str) -> String {
    Path::new(path).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| path.to_string())
}
