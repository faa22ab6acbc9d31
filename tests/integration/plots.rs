//! The pictures: `bgkmap eval --roc` (several maps on one plot) and `bgkmap export --format png
//! --slice z=H`, decoded and checked pixel by pixel against the maps they show.
#![allow(clippy::unwrap_used)]

use crate::common;

use common::{build, parse_csv, run_fail, run_ok_text, simulate};
use std::path::Path;

struct Image {
    width: u32,
    height: u32,
    rgb: Vec<[u8; 3]>,
}

impl Image {
    fn at(&self, x: i64, y: i64) -> [u8; 3] {
        self.rgb[(y * i64::from(self.width) + x) as usize]
    }
}

fn read_png(path: &Path) -> Image {
    let decoder = png::Decoder::new(std::fs::File::open(path).unwrap());
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = match info.color_type {
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => panic!("unexpected colour type {other:?}"),
    };
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let rgb = buf[..info.buffer_size()].chunks(channels).map(|c| [c[0], c[1], c[2]]).collect();
    Image { width: info.width, height: info.height, rgb }
}

#[test]
fn eval_roc_draws_every_map_on_one_plot() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 4);
    build(dir, "truncate.bgkmap", &["--max-range", "8"], &sim.scans);
    build(dir, "drop.bgkmap", &["--max-range", "8", "--range-mode", "drop"], &sim.scans);
    let text = run_ok_text(
        dir,
        ["eval", "truncate.bgkmap", "drop.bgkmap", "--truth", &sim.truth, "--roc", "roc.png"],
    );
    assert_eq!(text.lines().count(), 2, "{text}");
    let img = read_png(&dir.join("roc.png"));
    assert_eq!((img.width, img.height), (800, 800));
    let not_white = img.rgb.iter().filter(|p| **p != [255, 255, 255]).count();
    let total = img.rgb.len();
    assert!(not_white > total / 50 && not_white < total / 2, "{not_white} of {total} pixels drawn");
    // One colour per map (the first two of the palette), each a curve plus its legend line.
    for colour in [[31, 119, 180], [255, 127, 14]] {
        let n = img.rgb.iter().filter(|p| **p == colour).count();
        assert!(n > 800, "{n} pixels of curve colour {colour:?}");
    }
    let third = img.rgb.iter().filter(|p| **p == [44, 160, 44]).count();
    assert_eq!(third, 0, "no third curve");
}

/// From `wrote …, cells x A..=B, y C..=D, N px per cell, occupancy panel at X,Y, variance panel
/// at X,Y`: the key bounds, pixels per cell and the two panels' corners.
fn layout(line: &str) -> ([i64; 4], i64, [i64; 2], [i64; 2]) {
    let tail = &line[line.find("cells x ").unwrap()..];
    let v: Vec<i64> = tail
        .split(|c: char| !(c.is_ascii_digit() || c == '-'))
        .filter(|t| !t.is_empty())
        .map(|t| t.parse().unwrap())
        .collect();
    assert_eq!(v.len(), 9, "{line}");
    ([v[0], v[1], v[2], v[3]], v[4], [v[5], v[6]], [v[7], v[8]])
}

#[test]
fn export_png_slice_shows_each_cell_of_the_layer() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 3);
    build(dir, "m.bgkmap", &[], &sim.scans);
    let out =
        run_ok_text(dir, ["export", "m.bgkmap", "--format", "png", "--slice", "z=1.0", "--out", "s.png"]);
    let ([x0, x1, y0, y1], px, occ, var) = layout(out.trim());
    let img = read_png(&dir.join("s.png"));
    assert!(img.width as i64 > 2 * (x1 - x0 + 1) * px && img.height as i64 > (y1 - y0 + 1) * px);
    // Every cell of layer z = 1.0 m (key 10) with evidence, from the CSV export.
    let csv = run_ok_text(dir, ["export", "m.bgkmap", "--format", "csv"]);
    let rows: Vec<_> = parse_csv(&csv).into_iter().map(|(r, _)| r).filter(|r| r.key()[2] == 10).collect();
    assert!(rows.len() > 500, "{} cells in the layer", rows.len());
    let mut dark = 0;
    for r in &rows {
        let [kx, ky, _] = r.key().map(i64::from);
        let (cx, cy) = ((kx - x0) * px + px / 2, (y1 - ky) * px + px / 2);
        let g = (255.0 * (1.0 - r.probability)).round() as u8;
        assert_eq!(img.at(occ[0] + cx, occ[1] + cy), [g, g, g], "cell {kx},{ky} p={}", r.probability);
        let v = img.at(var[0] + cx, var[1] + cy);
        assert!(v[0] != v[1] || v[1] != v[2], "the variance panel is in colour at {kx},{ky}: {v:?}");
        dark += usize::from(r.probability > 0.7);
    }
    assert!(dark > 50, "{dark} occupied cells in the layer");
    let with_evidence = rows.len() as i64;
    let bbox_cells = (x1 - x0 + 1) * (y1 - y0 + 1);
    let grey = (0..bbox_cells)
        .filter(|i| {
            img.at(occ[0] + (i % (x1 - x0 + 1)) * px + px / 2, occ[1] + (i / (x1 - x0 + 1)) * px + px / 2)
                == [205, 218, 236]
        })
        .count() as i64;
    assert_eq!(grey, bbox_cells - with_evidence, "cells without evidence are pale blue");

    run_fail(
        dir,
        ["export", "m.bgkmap", "--format", "png", "--slice", "z=50", "--out", "t.png"],
        &["no cells with evidence"],
    );
    run_fail(dir, ["export", "m.bgkmap", "--format", "png", "--out", "t.png"], &["--slice"]);
    run_fail(dir, ["export", "m.bgkmap", "--format", "png", "--slice", "z=1"], &["--out"]);
    run_fail(dir, ["export", "m.bgkmap", "--format", "csv", "--slice", "z=1"], &["only for --format png"]);
    run_fail(
        dir,
        ["export", "m.bgkmap", "--format", "png", "--slice", "y=1", "--out", "t.png"],
        &["z=HEIGHT"],
    );
    common::assert_no_output(dir, "t.png");
}
