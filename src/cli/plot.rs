//! ROC curve plots (PNG) for `bgkmap eval`.
//!
//! Text is rendered with DejaVu Sans embedded in the binary
//! (`src/cli/fonts/DejaVuSans.ttf`, license in `src/cli/fonts/LICENSE-DejaVu.txt`)
//! through plotters' `ab_glyph` backend, so plotting needs no system fonts,
//! fontconfig or freetype.

use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Context, anyhow, ensure};
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

use crate::eval::Roc;

/// One curve of a ROC plot.
#[derive(Debug, Clone)]
pub struct RocCurve<'a> {
    /// Legend label; the AUC is appended as ` (AUC 0.9522)`.
    pub label: String,
    /// The curve.
    pub roc: &'a Roc,
}

/// Width and height of the PNG, in pixels.
const SIZE_PX: u32 = 800;

/// Curves with more points than this are decimated before drawing. At 800 px
/// the kept points are well under a pixel apart, so the shape is preserved.
const MAX_DRAWN_POINTS: usize = 2000;

/// DejaVu Sans 2.37 (Bitstream Vera license, see `src/cli/fonts/LICENSE-DejaVu.txt`).
static DEJAVU_SANS: &[u8] = include_bytes!("fonts/DejaVuSans.ttf");

/// The font family name the embedded font is registered under; plotters'
/// `FontFamily::SansSerif` resolves to it.
pub(crate) const FONT: &str = "sans-serif";

/// Colour-blind-friendly categorical colours (Tableau 10), cycled per curve.
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// Registers the embedded font with plotters, once per process.
pub(crate) fn ensure_font() -> anyhow::Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| register_font(FONT, FontStyle::Normal, DEJAVU_SANS).is_ok());
    ensure!(ok, "the embedded DejaVu Sans font could not be parsed");
    Ok(())
}

/// Draws the ROC curves (several maps on one plot) with "label (AUC 0.9522)" in
/// the legend, axes "false positive rate"/"true positive rate", the chance
/// diagonal, to a PNG of 800×800.
///
/// Curves with many points are decimated to at most about 2000 points for
/// drawing; the AUC in the legend is the one computed on the full curve.
///
/// # Errors
///
/// If the embedded font cannot be loaded, or drawing or writing the PNG fails
/// (e.g. the parent directory does not exist).
pub fn write_roc_png(path: &Path, title: &str, curves: &[RocCurve<'_>]) -> anyhow::Result<()> {
    ensure_font()?;
    draw(path, title, curves).with_context(|| format!("writing ROC plot {}", path.display()))
}

fn draw(path: &Path, title: &str, curves: &[RocCurve<'_>]) -> anyhow::Result<()> {
    // plotters' drawing errors carry the backend error type; flatten to text.
    let err = |e: &dyn std::fmt::Display| anyhow!("{e}");

    let root = BitMapBackend::new(path, (SIZE_PX, SIZE_PX)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;

    let mut chart = ChartBuilder::on(&root)
        .caption(title, (FONT, 26))
        .margin(24)
        .x_label_area_size(60)
        .y_label_area_size(70)
        .build_cartesian_2d(0f64..1f64, 0f64..1f64)
        .map_err(|e| err(&e))?;

    chart
        .configure_mesh()
        .x_labels(11)
        .y_labels(11)
        .x_label_formatter(&|x| format!("{x:.1}"))
        .y_label_formatter(&|y| format!("{y:.1}"))
        .x_desc("false positive rate")
        .y_desc("true positive rate")
        .axis_desc_style((FONT, 20))
        .label_style((FONT, 16))
        .max_light_lines(1)
        .light_line_style(RGBColor(242, 242, 242))
        .bold_line_style(RGBColor(215, 215, 215))
        .draw()
        .map_err(|e| err(&e))?;

    let chance_style = ShapeStyle::from(&RGBColor(120, 120, 120)).stroke_width(1);
    chart
        .draw_series(DashedLineSeries::new([(0.0, 0.0), (1.0, 1.0)], 8, 6, chance_style))
        .map_err(|e| err(&e))?
        .label("chance (AUC 0.5)")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], chance_style));

    for (i, curve) in curves.iter().enumerate() {
        let style = PALETTE[i % PALETTE.len()].stroke_width(2);
        chart
            .draw_series(LineSeries::new(decimate(&curve.roc.points, MAX_DRAWN_POINTS), style))
            .map_err(|e| err(&e))?
            .label(format!("{} (AUC {:.4})", curve.label, curve.roc.auc))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], style));
    }

    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .margin(12)
        .label_font((FONT, 18))
        .background_style(WHITE.mix(0.9))
        .border_style(RGBColor(160, 160, 160))
        .draw()
        .map_err(|e| err(&e))?;

    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// Thins a monotone polyline to at most `max` points (`max >= 2`), keeping the
/// first and last points and a point whenever the Manhattan path length since
/// the last kept point reaches `total / (max - 2)`. Every dropped point lies
/// within that step of the kept polyline, so the shape is preserved far below
/// pixel size for `max` in the thousands.
fn decimate(points: &[(f64, f64)], max: usize) -> Vec<(f64, f64)> {
    let max = max.max(3);
    if points.len() <= max {
        return points.to_vec();
    }
    let manhattan = |a: (f64, f64), b: (f64, f64)| (b.0 - a.0).abs() + (b.1 - a.1).abs();
    let total: f64 = points.windows(2).map(|w| manhattan(w[0], w[1])).sum();
    let step = total / (max - 2) as f64;

    let (first, rest) = match points.split_first() {
        Some(split) => split,
        None => return Vec::new(),
    };
    let mut out = Vec::with_capacity(max);
    out.push(*first);
    let mut prev = *first;
    let mut since_kept = 0.0;
    let last_index = rest.len().saturating_sub(1);
    for (i, &p) in rest.iter().enumerate() {
        since_kept += manhattan(prev, p);
        prev = p;
        if i == last_index || since_kept >= step {
            out.push(p);
            since_kept = 0.0;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::roc;

    #[test]
    fn decimate_keeps_ends_and_bounds_count() {
        let n = 100_000;
        let pts: Vec<(f64, f64)> = (0..=n)
            .map(|i| {
                let x = i as f64 / n as f64;
                (x, x.sqrt())
            })
            .collect();
        let d = decimate(&pts, MAX_DRAWN_POINTS);
        assert!(d.len() <= MAX_DRAWN_POINTS, "{} points", d.len());
        assert!(d.len() > MAX_DRAWN_POINTS / 2, "{} points", d.len());
        assert_eq!(d.first(), pts.first());
        assert_eq!(d.last(), pts.last());
        // Kept points stay on the curve and in order.
        for w in d.windows(2) {
            assert!(w[1].0 > w[0].0);
        }
        // Short curves pass through unchanged.
        assert_eq!(decimate(&pts[..10], MAX_DRAWN_POINTS), pts[..10].to_vec());
    }

    #[test]
    fn writes_png_with_two_curves() {
        // A good and a mediocre classifier, with enough points to exercise the
        // decimation on the first.
        let mut good: Vec<(f64, bool)> = (0..20_000)
            .map(|i| {
                let label = i % 10 == 0;
                let base = (i as f64 * 0.618_033_988_749_895).fract();
                (if label { 0.35 + 0.65 * base } else { 0.7 * base }, label)
            })
            .collect();
        let mut poor: Vec<(f64, bool)> = (0..200)
            .map(|i| {
                let label = i % 4 == 0;
                let base = (i as f64 * 0.414_213_562_373_095).fract();
                (if label { 0.2 + 0.8 * base } else { base }, label)
            })
            .collect();
        let good = roc(&mut good).expect("roc");
        let poor = roc(&mut poor).expect("roc");
        assert!(good.points.len() > MAX_DRAWN_POINTS);

        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("roc.png");
        write_roc_png(
            &path,
            "ROC on sim_structured (unknown = 0.5)",
            &[
                RocCurve { label: "bgkmap truncate".to_string(), roc: &good },
                RocCurve { label: "la3dm drop".to_string(), roc: &poor },
            ],
        )
        .expect("write png");

        let bytes = std::fs::read(&path).expect("read png");
        assert!(bytes.starts_with(b"\x89PNG\r\n\x1a\n"), "not a PNG");
        assert!(bytes.len() > 5 * 1024, "PNG only {} bytes", bytes.len());

        if let Some(keep) = std::env::var_os("BGKMAP_KEEP_PLOT") {
            std::fs::copy(&path, keep).expect("copy png");
        }
    }

    #[test]
    fn missing_directory_is_an_error() {
        let mut s = vec![(0.9, true), (0.1, false)];
        let r = roc(&mut s).expect("roc");
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("no/such/dir/roc.png");
        let res = write_roc_png(&path, "t", &[RocCurve { label: "x".into(), roc: &r }]);
        assert!(res.is_err());
    }
}
