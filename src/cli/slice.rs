//! `bgkmap export --format png --slice z=H`: a top-down picture of one layer of cells, with the
//! occupancy probability (white = free, black = occupied) on the left and the variance
//! (viridis, 0 to ¼) on the right; cells without evidence are pale blue. North (+y) is up.
//!
//! Text uses the embedded DejaVu Sans (see [`super::plot`]), drawn in dark blue so no label
//! pixel is a pure grey like the cells.

use super::plot::{FONT, ensure_font};
use crate::core::key::BLOCK_CELLS;
use crate::core::{CellKey, EvidenceMap};
use anyhow::{Context, Result, anyhow, bail, ensure};
use plotters::prelude::*;
use std::path::Path;

/// Colour of cells without evidence: a pale blue, so it is never one of the probability greys.
pub const NO_EVIDENCE: RGBColor = RGBColor(205, 218, 236);
const TEXT: RGBColor = RGBColor(20, 30, 110);
/// Pixels between and around the panels, above them (titles) and below (colour bars).
const MARGIN_PX: u32 = 24;
const TITLE_PX: u32 = 44;
const LEGEND_PX: u32 = 64;
/// The larger panel edge aims at this many pixels.
const PANEL_TARGET_PX: u32 = 640;

/// Viridis at 0, ¼, ½, ¾ and 1.
const VIRIDIS: [(f64, f64, f64); 5] = [
    (0.267, 0.005, 0.329),
    (0.229, 0.322, 0.546),
    (0.128, 0.567, 0.551),
    (0.369, 0.789, 0.383),
    (0.993, 0.906, 0.144),
];

/// Parses `z=H` (metres).
pub fn parse_slice(s: &str) -> Result<f64, String> {
    let v = s.strip_prefix("z=").ok_or_else(|| format!("expected z=HEIGHT (m), got {s:?}"))?;
    v.trim()
        .parse::<f64>()
        .ok()
        .filter(|z| z.is_finite())
        .ok_or_else(|| format!("not a finite height: {v:?}"))
}

/// Grey shade of a probability: 255 (white) at p = 0, 0 (black) at p = 1.
pub fn occupancy_shade(p: f64) -> u8 {
    (255.0 * (1.0 - p.clamp(0.0, 1.0))).round() as u8
}

/// The viridis colour of a variance (0 to ¼).
pub fn variance_colour(var: f64) -> RGBColor {
    let x = (var / 0.25).clamp(0.0, 1.0) * 4.0;
    let i = (x.floor() as usize).min(3);
    let f = x - i as f64;
    let (a, b) = (VIRIDIS[i], VIRIDIS[i + 1]);
    let mix = |u: f64, v: f64| (255.0 * (u * (1.0 - f) + v * f)).round() as u8;
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// One layer of cells: probability and variance per cell with evidence.
#[derive(Debug)]
pub struct Slice {
    pub z_key: i32,
    /// Inclusive cell-key bounds in x and y.
    pub x: (i32, i32),
    pub y: (i32, i32),
    pub cells: Vec<(CellKey, f64, f64)>,
}

/// The cells with evidence in the layer containing height `z_m`, optionally only those whose
/// centres lie in the xy box `[lo, hi]` (m).
pub fn slice(map: &EvidenceMap, z_m: f64, xy_box: Option<([f64; 2], [f64; 2])>) -> Result<Slice> {
    let params = map.params();
    let res = params.resolution_m;
    let z_key = CellKey::from_point([0.0, 0.0, z_m], res)
        .ok_or_else(|| anyhow!("z = {z_m} is outside the key range"))?
        .z;
    let th = params.thresholds;
    let mut cells = Vec::new();
    for key in map.block_keys_sorted().into_iter().filter(|k| k.z == z_key >> 3) {
        let Some(block) = map.block(key) else { continue };
        for i in 0..BLOCK_CELLS {
            let cell = key.cell(i);
            if cell.z != z_key || block.get(i).is_empty() {
                continue;
            }
            let c = cell.centre(res);
            if xy_box
                .is_some_and(|(lo, hi)| !(lo[0] <= c[0] && c[0] <= hi[0] && lo[1] <= c[1] && c[1] <= hi[1]))
            {
                continue;
            }
            let e = map.estimate(cell, &th);
            cells.push((cell, e.probability, e.variance));
        }
    }
    ensure!(!cells.is_empty(), "the slice at z = {z_m} m (cell layer {z_key}) holds no cells with evidence");
    let bounds = |f: fn(&CellKey) -> i32| {
        let v = cells.iter().map(|(k, _, _)| f(k));
        (v.clone().min().unwrap_or(0), v.max().unwrap_or(0))
    };
    Ok(Slice { z_key, x: bounds(|k| k.x), y: bounds(|k| k.y), cells })
}

/// Where things are drawn.
#[derive(Debug, Clone, Copy)]
pub struct Layout {
    pub cell_px: u32,
    pub width_px: u32,
    pub height_px: u32,
    /// Top-left corners of the occupancy and variance panels.
    pub occupancy_at: (u32, u32),
    pub variance_at: (u32, u32),
}

impl Slice {
    pub fn layout(&self) -> Layout {
        let (nx, ny) = ((self.x.1 - self.x.0 + 1) as u32, (self.y.1 - self.y.0 + 1) as u32);
        let cell_px = (PANEL_TARGET_PX / nx.max(ny)).clamp(1, 16);
        let (w, h) = (nx * cell_px, ny * cell_px);
        Layout {
            cell_px,
            width_px: 2 * w + 3 * MARGIN_PX,
            height_px: TITLE_PX + h + LEGEND_PX,
            occupancy_at: (MARGIN_PX, TITLE_PX),
            variance_at: (2 * MARGIN_PX + w, TITLE_PX),
        }
    }

    /// Top-left pixel of a cell inside a panel whose corner is `at`.
    pub fn cell_px(&self, layout: &Layout, at: (u32, u32), k: CellKey) -> (i32, i32) {
        let s = layout.cell_px as i32;
        (at.0 as i32 + (k.x - self.x.0) * s, at.1 as i32 + (self.y.1 - k.y) * s)
    }
}

/// Draws the slice to a PNG (layout: [`Slice::layout`]); returns the layout.
pub fn write_slice_png(path: &Path, slice: &Slice, z_m: f64) -> Result<Layout> {
    ensure_font()?;
    draw(path, slice, z_m).with_context(|| format!("writing slice picture {}", path.display()))
}

fn draw(path: &Path, slice: &Slice, z_m: f64) -> Result<Layout> {
    let err = |e: &dyn std::fmt::Display| anyhow!("{e}");
    let l = slice.layout();
    let root = BitMapBackend::new(path, (l.width_px, l.height_px)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (w, h) = (l.variance_at.0 - l.occupancy_at.0 - MARGIN_PX, l.height_px - TITLE_PX - LEGEND_PX);
    let s = l.cell_px as i32;
    for at in [l.occupancy_at, l.variance_at] {
        let (x, y) = (at.0 as i32, at.1 as i32);
        root.draw(&Rectangle::new([(x, y), (x + w as i32, y + h as i32)], NO_EVIDENCE.filled()))
            .map_err(|e| err(&e))?;
    }
    for &(k, p, var) in &slice.cells {
        let g = occupancy_shade(p);
        for (at, colour) in [(l.occupancy_at, RGBColor(g, g, g)), (l.variance_at, variance_colour(var))] {
            let (x, y) = slice.cell_px(&l, at, k);
            root.draw(&Rectangle::new([(x, y), (x + s, y + s)], colour.filled())).map_err(|e| err(&e))?;
        }
    }
    let title = (FONT, 18).into_font().color(&TEXT);
    let label = (FONT, 14).into_font().color(&TEXT);
    let panels = [
        (l.occupancy_at, format!("occupancy probability, z = {z_m:.2} m"), "0 (free)", "1 (occupied)"),
        (l.variance_at, "variance".to_string(), "0", "0.25"),
    ];
    for (i, (at, text, lo, hi)) in panels.into_iter().enumerate() {
        let (x, y) = (at.0 as i32, at.1 as i32);
        root.draw(&Text::new(text, (x, 12), title.clone())).map_err(|e| err(&e))?;
        let bar_y = y + h as i32 + 12;
        let bar_w = (w as i32).min(320);
        for dx in 0..bar_w {
            let t = f64::from(dx) / f64::from(bar_w - 1).max(1.0);
            let c = if i == 0 {
                let g = occupancy_shade(t);
                RGBColor(g, g, g)
            } else {
                variance_colour(t * 0.25)
            };
            root.draw(&Rectangle::new([(x + dx, bar_y), (x + dx + 1, bar_y + 12)], c.filled()))
                .map_err(|e| err(&e))?;
        }
        root.draw(&Text::new(lo, (x, bar_y + 18), label.clone())).map_err(|e| err(&e))?;
        let hi_x = x + bar_w - 8 * hi.len() as i32;
        root.draw(&Text::new(hi, (hi_x, bar_y + 18), label.clone())).map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(l)
}

/// `export --format png`: checks the arguments, draws, and reports the layout on stdout.
pub fn export_png(
    map: &EvidenceMap,
    slice_z: Option<f64>,
    bbox: Option<([f64; 3], [f64; 3])>,
    out: Option<&Path>,
) -> Result<()> {
    let Some(z) = slice_z else { bail!("--format png needs --slice z=HEIGHT") };
    let Some(out) = out else { bail!("--format png needs --out FILE.png") };
    let s = slice(map, z, bbox.map(|(lo, hi)| ([lo[0], lo[1]], [hi[0], hi[1]])))?;
    // The image encoder picks the format from the extension: keep `.png` on the temporary file.
    let mut tmp = crate::store::temp_sibling(out).into_os_string();
    tmp.push(".png");
    let tmp = std::path::PathBuf::from(tmp);
    let layout = match write_slice_png(&tmp, &s, z) {
        Ok(l) => l,
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
    };
    std::fs::rename(&tmp, out).with_context(|| format!("{}: cannot write", out.display()))?;
    println!(
        "wrote {}: z = {z} m (cell layer {}), cells x {}..={}, y {}..={}, {} px per cell, \
         occupancy panel at {},{}, variance panel at {},{}",
        out.display(),
        s.z_key,
        s.x.0,
        s.x.1,
        s.y.0,
        s.y.1,
        layout.cell_px,
        layout.occupancy_at.0,
        layout.occupancy_at.1,
        layout.variance_at.0,
        layout.variance_at.1
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slice_spec_and_colours() {
        assert_eq!(parse_slice("z=1.5"), Ok(1.5));
        assert!(parse_slice("x=1").is_err());
        assert!(parse_slice("z=nan").is_err());
        assert_eq!((occupancy_shade(0.0), occupancy_shade(1.0), occupancy_shade(0.5)), (255, 0, 128));
        assert_eq!(variance_colour(0.0), RGBColor(68, 1, 84));
        assert_eq!(variance_colour(1.0), RGBColor(253, 231, 37));
    }
}
