//! `bgkmap export`: CSV, OctoMap `.bt`, PLY, and a PNG picture of one layer (see [`super::slice`]).

use super::args::{ThresholdArgs, parse_floats, write_output};
use crate::core::query::{BoxQuery, query_box};
use crate::core::{CellKey, CellState, EvidenceMap};
use crate::io::octomap::{BtTree, write_bt};
use crate::io::ply::{PlyVertex, write_ply_points};
use crate::store::load_map;
use anyhow::Result;
use clap::{Args, ValueEnum};
use std::fmt::Write as _;
use std::path::PathBuf;

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Format {
    Csv,
    Bt,
    Ply,
    /// A top-down picture of one layer of cells (needs --slice and --out).
    Png,
}

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// Map file.
    pub map: PathBuf,
    #[arg(long, value_enum)]
    pub format: Format,
    /// Only cells inside MINX,MINY,MINZ,MAXX,MAXY,MAXZ (m, world frame).
    #[arg(long = "box", value_parser = parse_box, allow_hyphen_values = true)]
    pub bbox: Option<([f64; 3], [f64; 3])>,
    /// Output file (stdout when absent; required for png).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// For png: the layer to draw, as z=HEIGHT (m).
    #[arg(long, value_parser = super::slice::parse_slice, allow_hyphen_values = true)]
    pub slice: Option<f64>,
    #[command(flatten)]
    pub thresholds: ThresholdArgs,
}

fn parse_box(s: &str) -> Result<([f64; 3], [f64; 3]), String> {
    let v = parse_floats(s, 6)?;
    if v[0] > v[3] || v[1] > v[4] || v[2] > v[5] {
        return Err("box min must not exceed max".into());
    }
    Ok(([v[0], v[1], v[2]], [v[3], v[4], v[5]]))
}

/// One exported cell.
struct Row {
    cell: CellKey,
    probability: f64,
    variance: f64,
    state: CellState,
}

pub fn run(a: ExportArgs) -> Result<()> {
    let map = load_map(&a.map)?;
    let th = a.thresholds.resolve(map.params().thresholds)?;
    if !matches!(a.format, Format::Png) {
        anyhow::ensure!(a.slice.is_none(), "--slice is only for --format png");
    }
    let rows = rows(&map, a.bbox, &th)?;
    let res = map.params().resolution_m;
    let bytes = match a.format {
        Format::Csv => csv(&rows, res).into_bytes(),
        Format::Bt => {
            let cells = rows.iter().filter_map(|r| match r.state {
                CellState::Occupied => Some((r.cell, true)),
                CellState::Free => Some((r.cell, false)),
                CellState::Unknown => None,
            });
            write_bt(&BtTree::from_cells(res, cells, true)?)
        }
        Format::Ply => ply(&rows, res),
        Format::Png => return super::slice::export_png(&map, a.slice, a.bbox, a.out.as_deref()),
    };
    write_output(a.out.as_ref(), &bytes)
}

/// Every cell with evidence (inside the box, if given), sorted by key (x, then y, then z).
fn rows(
    map: &EvidenceMap,
    bbox: Option<([f64; 3], [f64; 3])>,
    th: &crate::core::Thresholds,
) -> Result<Vec<Row>> {
    let mut rows = Vec::new();
    if let Some((min_world, max_world)) = bbox {
        let q = BoxQuery { min_world, max_world, state: None, coarsen: 0 };
        for c in query_box(map, &q, th, u64::MAX)? {
            let e = c.estimate;
            rows.push(Row {
                cell: c.min_cell,
                probability: e.probability,
                variance: e.variance,
                state: e.state,
            });
        }
    } else {
        for key in map.block_keys_sorted() {
            let Some(block) = map.block(key) else { continue };
            for i in 0..crate::core::key::BLOCK_CELLS {
                if !block.get(i).is_empty() {
                    let cell = key.cell(i);
                    let e = map.estimate(cell, th);
                    rows.push(Row { cell, probability: e.probability, variance: e.variance, state: e.state });
                }
            }
        }
    }
    rows.sort_unstable_by_key(|r| r.cell);
    Ok(rows)
}

/// Decimal places that show cell centres exactly at this resolution (0.1 → 2: "0.05").
fn centre_decimals(res: f64) -> usize {
    (1..=9).find(|&d| ((res / 2.0) * 10f64.powi(d)).fract().abs() < 1e-6).unwrap_or(9) as usize
}

fn csv(rows: &[Row], res: f64) -> String {
    let d = centre_decimals(res);
    let mut s = String::with_capacity(rows.len() * 48 + 40);
    s.push_str("x,y,z,size,probability,variance\n");
    for r in rows {
        let c = r.cell.centre(res);
        let _ = writeln!(s, "{:.d$},{:.d$},{:.d$},{res},{},{}", c[0], c[1], c[2], r.probability, r.variance);
    }
    s
}

fn ply(rows: &[Row], res: f64) -> Vec<u8> {
    let verts: Vec<PlyVertex> = rows
        .iter()
        .filter(|r| r.state == CellState::Occupied)
        .map(|r| {
            let c = r.cell.centre(res);
            let p = r.probability;
            let shade = (255.0 * p).round() as u8;
            PlyVertex {
                position: [c[0] as f32, c[1] as f32, c[2] as f32],
                color: [shade, 64, 255 - shade],
                probability: p as f32,
            }
        })
        .collect();
    write_ply_points(&verts, &format!("bgkmap occupied cells, res {res}"))
}

#[cfg(test)]
mod tests {
    #[test]
    fn centre_decimals_show_centres_exactly() {
        assert_eq!(super::centre_decimals(0.1), 2);
        assert_eq!(super::centre_decimals(0.2), 1);
        assert_eq!(super::centre_decimals(0.05), 3);
    }
}
