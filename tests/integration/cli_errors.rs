#![allow(clippy::unwrap_used)]
//! Bad input to the `bgkmap` command line: every failure exits non-zero with an `error: …` that
//! names the problem, and leaves no output (nor a temporary sibling) behind.
// The tests run the `bgkmap` binary, which needs the `cli` feature.
#![cfg(feature = "cli")]

use crate::common;

use bgkmap::io::pcd::read_pcd;
use common::{assert_no_output, build, export_csv, run_fail, run_fail_code, run_ok, simulate};
use std::path::Path;

/// Offset of the first data byte of a PCD file (just after the `DATA …` line).
fn data_offset(bytes: &[u8]) -> usize {
    let at = bytes.windows(5).position(|w| w == b"DATA ").unwrap();
    at + bytes[at..].iter().position(|&b| b == b'\n').unwrap() + 1
}

/// A PCD (binary x y z) of `points` with no VIEWPOINT line.
fn pcd_without_viewpoint(points: &[[f32; 3]]) -> Vec<u8> {
    let n = points.len();
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n\
         COUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary\n"
    )
    .into_bytes();
    for v in points.iter().flatten() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

fn write(dir: &Path, name: &str, bytes: &[u8]) {
    std::fs::write(dir.join(name), bytes).unwrap();
}

#[test]
fn truncated_pcd_is_reported() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 2);
    let bytes = std::fs::read(dir.join(&sim.scans[0])).unwrap();
    let start = data_offset(&bytes);
    let cut = start + (bytes.len() - start) / 2 + 5; // mid-point, not on a point boundary
    write(dir, "cut.pcd", &bytes[..cut]);

    run_fail_code(dir, ["build", "--out", "out.bgkmap", "cut.pcd"], 1, &["cut.pcd", "truncated"]);
    assert_no_output(dir, "out.bgkmap");
    // Also when the bad scan comes after good ones.
    run_fail(dir, ["build", "--out", "out.bgkmap", &sim.scans[0], &sim.scans[1], "cut.pcd"], &["truncated"]);
    assert_no_output(dir, "out.bgkmap");
    // Only the header.
    write(dir, "header_only.pcd", &bytes[..start]);
    run_fail(dir, ["build", "--out", "out.bgkmap", "header_only.pcd"], &["header_only.pcd", "truncated"]);
    assert_no_output(dir, "out.bgkmap");
}

#[test]
fn malformed_pcd_header_is_reported() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write(dir, "garbage.pcd", b"this is not a point cloud\n\x00\x01\x02 at all\n");
    run_fail_code(dir, ["build", "--out", "out.bgkmap", "garbage.pcd"], 1, &["garbage.pcd", "header"]);
    assert_no_output(dir, "out.bgkmap");
    write(dir, "empty.pcd", b"");
    run_fail_code(dir, ["build", "--out", "out.bgkmap", "empty.pcd"], 1, &["empty.pcd"]);
    assert_no_output(dir, "out.bgkmap");
    run_fail_code(dir, ["build", "--out", "out.bgkmap", "missing.pcd"], 1, &["missing.pcd"]);
    assert_no_output(dir, "out.bgkmap");
}

#[test]
fn pcd_without_viewpoint_needs_origin() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 1);
    let cloud = read_pcd(&std::fs::read(dir.join(&sim.scans[0])).unwrap()).unwrap();
    let vp = cloud.viewpoint.unwrap();
    write(dir, "novp.pcd", &pcd_without_viewpoint(&cloud.points));

    run_fail_code(
        dir,
        ["build", "--out", "out.bgkmap", "novp.pcd"],
        1,
        &["novp.pcd", "VIEWPOINT", "--origin"],
    );
    assert_no_output(dir, "out.bgkmap");

    run_ok(dir, ["build", "--out", "zero.bgkmap", "--origin", "0,0,0", "novp.pcd"]);
    assert!(dir.join("zero.bgkmap").is_file());

    // With the VIEWPOINT's translation as --origin, the map equals the original scan's.
    let origin = format!("{},{},{}", vp[0], vp[1], vp[2]);
    run_ok(dir, ["build", "--out", "novp.bgkmap", "--origin", &origin, "novp.pcd"]);
    build(dir, "orig.bgkmap", &[], &sim.scans);
    assert!(
        export_csv(dir, "novp.bgkmap") == export_csv(dir, "orig.bgkmap"),
        "--origin map differs from VIEWPOINT map"
    );
}

#[test]
fn merge_of_different_parameters_names_the_parameter() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 2);
    build(dir, "ell.bgkmap", &["--ell", "0.3"], &sim.scans[..1]);
    build(dir, "default.bgkmap", &[], &sim.scans[1..]);
    run_fail_code(
        dir,
        ["merge", "ell.bgkmap", "default.bgkmap", "--out", "out.bgkmap"],
        1,
        &["ell", "differ"],
    );
    assert_no_output(dir, "out.bgkmap");
    run_fail_code(
        dir,
        ["merge", "default.bgkmap", "ell.bgkmap", "--out", "out.bgkmap"],
        1,
        &["ell", "differ"],
    );
    assert_no_output(dir, "out.bgkmap");
    // Points where they are against points at sub-cell centres: different evidence, no merge.
    build(dir, "exact.bgkmap", &["--sub-cells", "0"], &sim.scans[..1]);
    run_fail_code(
        dir,
        ["merge", "exact.bgkmap", "default.bgkmap", "--out", "out.bgkmap"],
        1,
        &["sub_cells: 0 vs 8", "differ"],
    );
    assert_no_output(dir, "out.bgkmap");
}

#[test]
fn wrong_map_files_are_rejected() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 1);
    build(dir, "good.bgkmap", &[], &sim.scans);

    // Another format version: SQLite keeps `user_version` big-endian at byte 60 of the header.
    let mut bytes = std::fs::read(dir.join("good.bgkmap")).unwrap();
    assert!(bytes.starts_with(b"SQLite format 3\0"));
    bytes[60..64].copy_from_slice(&99u32.to_be_bytes());
    write(dir, "v99.bgkmap", &bytes);
    run_fail_code(
        dir,
        ["export", "v99.bgkmap", "--format", "csv", "--out", "out.csv"],
        1,
        &["v99.bgkmap", "format version 99"],
    );
    assert_no_output(dir, "out.csv");
    run_fail(dir, ["merge", "good.bgkmap", "v99.bgkmap", "--out", "out.bgkmap"], &["format version 99"]);
    assert_no_output(dir, "out.bgkmap");

    // Not SQLite at all; an empty file (which SQLite would accept as an empty database).
    for (name, contents) in
        [("pcd.bgkmap", std::fs::read(dir.join(&sim.scans[0])).unwrap()), ("empty.bgkmap", vec![])]
    {
        write(dir, name, &contents);
        run_fail_code(
            dir,
            ["export", name, "--format", "csv", "--out", "out.csv"],
            1,
            &[name, "not a bgkmap map file"],
        );
        assert_no_output(dir, "out.csv");
        run_fail(dir, ["eval", name, "--truth", &sim.truth], &["not a bgkmap map file"]);
    }
    assert!(std::fs::read(dir.join("empty.bgkmap")).unwrap().is_empty(), "reading must not modify the file");

    // A missing map is not created by trying to read it.
    run_fail_code(dir, ["export", "missing.bgkmap", "--format", "csv"], 1, &["missing.bgkmap"]);
    assert!(!dir.join("missing.bgkmap").exists());
}

#[test]
fn invalid_parameters_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 1);
    let scan = sim.scans[0].as_str();
    for (flag, value, name) in [
        ("--resolution", "-1", "resolution"),
        ("--resolution", "0", "resolution"),
        ("--ell", "nan", "ell"),
        ("--ell", "inf", "ell"),
        ("--sf2", "-2", "sf2"),
        ("--p-occ", "1.5", "p_occ"),
        ("--sub-cells", "3", "sub_cells"),
        ("--sub-cells", "128", "sub_cells"),
    ] {
        // `--flag=value`: a bare `-1` would be read as an option by the argument parser.
        let arg = format!("{flag}={value}");
        run_fail_code(dir, ["build", "--out", "out.bgkmap", &arg, scan], 1, &["invalid parameter", name]);
        assert_no_output(dir, "out.bgkmap");
    }

    // A box with min > max is a usage error (exit code 2).
    build(dir, "map.bgkmap", &[], &sim.scans);
    run_fail_code(
        dir,
        ["export", "map.bgkmap", "--format", "csv", "--box", "1,1,1,0,2,2", "--out", "out.csv"],
        2,
        &["box", "min"],
    );
    assert_no_output(dir, "out.csv");
    run_fail_code(
        dir,
        ["export", "map.bgkmap", "--format", "csv", "--box", "0,0,0,1,1", "--out", "out.csv"],
        2,
        &["box"],
    );
    assert_no_output(dir, "out.csv");

    // Alternating in runs of no passes means nothing: a usage error, not a silent 1.
    run_fail_code(
        dir,
        ["bench", "ingest", "--threads", "2", "--alternate-every", "0"],
        2,
        &["--alternate-every"],
    );
    run_fail_code(dir, ["bench", "report", "--rounds", "0"], 2, &["--rounds"]);
    run_fail(
        dir,
        ["bench", "report", "--json-out", "no/such/dir/report.json"],
        &["cannot write", "report.json"],
    );
    // A bench that fails stops the report, naming the bench, its round and its own error.
    run_fail(
        dir,
        ["bench", "report", "--quick", "--rounds", "1", "missing.pcd"],
        &["bench sample", "round 1", "missing.pcd"],
    );
}

#[test]
fn failed_build_keeps_the_existing_map() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 2);
    build(dir, "map.bgkmap", &[], &sim.scans[..1]);
    let before = std::fs::read(dir.join("map.bgkmap")).unwrap();
    write(dir, "bad.pcd", b"VERSION 0.7\nFIELDS x y z\nDATA binary\n");

    run_fail(dir, ["build", "--out", "map.bgkmap", &sim.scans[1], "bad.pcd"], &["bad.pcd"]);
    assert!(std::fs::read(dir.join("map.bgkmap")).unwrap() == before, "the existing map was modified");
    // Same for a failing merge.
    build(dir, "ell.bgkmap", &["--ell", "0.3"], &sim.scans[1..]);
    run_fail(dir, ["merge", "ell.bgkmap", "map.bgkmap", "--out", "map.bgkmap"], &["ell"]);
    assert!(std::fs::read(dir.join("map.bgkmap")).unwrap() == before, "the existing map was modified");
    let stray: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp-"))
        .collect();
    assert!(stray.is_empty(), "stray temporary files: {stray:?}");
}
