#![allow(clippy::unwrap_used)]
//! Acceptance tests of the `bgkmap` command line on simulated data (always run): exactness of
//! build order / threads / merge, the export formats, eval, bench and demo.
// The tests run the `bgkmap` binary, which needs the `cli` feature.
#![cfg(feature = "cli")]

use crate::common;

use bgkmap::io::octomap::read_bt;
use common::{build, export_csv, json_number, parse_csv, run_ok, run_ok_text, simulate};
use std::collections::BTreeSet;

/// Evidence is a sum, so integration order, splitting into maps + merge, and threads must give
/// bit-identical maps; the CSV export (full f64 precision) shows any difference.
#[test]
fn order_threads_and_merge_are_exact_on_simulated_scans() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 8);
    let reversed: Vec<String> = sim.scans.iter().rev().cloned().collect();

    build(dir, "order.bgkmap", &[], &sim.scans);
    build(dir, "reverse.bgkmap", &[], &reversed);
    build(dir, "first.bgkmap", &[], &sim.scans[..4]);
    build(dir, "last.bgkmap", &[], &sim.scans[4..]);
    build(dir, "threads.bgkmap", &["--threads", "2"], &sim.scans);
    run_ok(dir, ["merge", "first.bgkmap", "last.bgkmap", "--out", "merged.bgkmap"]);

    let order = export_csv(dir, "order.bgkmap");
    let rows = parse_csv(&order);
    assert!(rows.len() > 1000, "only {} cells with evidence", rows.len());
    // Non-trivial: the map knows both occupied and free space.
    assert!(rows.iter().any(|(r, _)| r.probability > 0.7));
    assert!(rows.iter().any(|(r, _)| r.probability < 0.3));
    // Sorted by key, no duplicates.
    let keys: Vec<[i32; 3]> = rows.iter().map(|(r, _)| r.key()).collect();
    assert!(keys.windows(2).all(|w| w[0] < w[1]), "CSV rows are not sorted by (x, y, z) key");

    for other in ["reverse.bgkmap", "merged.bgkmap", "threads.bgkmap"] {
        let csv = export_csv(dir, other);
        assert!(csv == order, "{other}: CSV differs from the in-order build");
    }
}

#[test]
fn export_formats_bt_ply_box_and_out() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 4);
    build(dir, "map.bgkmap", &[], &sim.scans);
    let csv = export_csv(dir, "map.bgkmap");
    let rows = parse_csv(&csv);
    assert!(rows.len() > 1000);

    // A reader that stops early (`| head -1`) is not an error: exit 0 and nothing on stderr.
    {
        use std::io::BufRead;
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_bgkmap"))
            .current_dir(dir)
            .args(["export", "map.bgkmap", "--format", "csv"])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut first = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut first).unwrap();
        assert_eq!(first.trim_end(), "x,y,z,size,probability,variance");
        assert!(csv.len() > 1 << 20, "the export must outgrow the pipe's buffer for this test");
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success() && stderr.is_empty(), "{:?}: {stderr}", out.status);
    }

    // --out writes the same bytes as stdout.
    run_ok(dir, ["export", "map.bgkmap", "--format", "csv", "--out", "map.csv"]);
    assert!(std::fs::read(dir.join("map.csv")).unwrap() == csv.as_bytes(), "--out CSV differs from stdout");

    // .bt: resolution 0.1, and its labels follow the state rule (defaults p_occ 0.7, p_free 0.3).
    let bt_stdout = run_ok(dir, ["export", "map.bgkmap", "--format", "bt"]);
    run_ok(dir, ["export", "map.bgkmap", "--format", "bt", "--out", "map.bt"]);
    let bt_bytes = std::fs::read(dir.join("map.bt")).unwrap();
    assert!(bt_bytes == bt_stdout, "--out .bt differs from stdout");
    let tree = read_bt(&bt_bytes).unwrap();
    assert!((tree.resolution - 0.1).abs() < 1e-12, "resolution {}", tree.resolution);
    assert!(tree.occupied_leaves() > 0);
    let prob: std::collections::HashMap<[i32; 3], f64> =
        rows.iter().map(|(r, _)| (r.key(), r.probability)).collect();
    let mut bt_occupied = BTreeSet::new();
    let mut bt_free = 0usize;
    for (cell, occupied) in tree.cells() {
        let key = [cell.x, cell.y, cell.z];
        let p = *prob.get(&key).unwrap_or_else(|| panic!(".bt cell {key:?} has no evidence in the CSV"));
        if occupied {
            assert!(p > 0.7, "occupied .bt cell {key:?} has p = {p}");
            bt_occupied.insert(key);
        } else {
            assert!(p < 0.3, "free .bt cell {key:?} has p = {p}");
            bt_free += 1;
        }
    }
    assert!(bt_free > 0, "the .bt has no free cells");
    let csv_occupied: BTreeSet<[i32; 3]> =
        rows.iter().filter(|(r, _)| r.probability > 0.7).map(|(r, _)| r.key()).collect();
    assert!(bt_occupied == csv_occupied, "occupied cells of the .bt and the CSV differ");

    // PLY: binary little-endian, one vertex per occupied cell.
    let ply = run_ok(dir, ["export", "map.bgkmap", "--format", "ply"]);
    assert!(
        ply.starts_with(b"ply\nformat binary_little_endian 1.0\n"),
        "PLY header: {:?}",
        &ply[..40.min(ply.len())]
    );
    let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap();
    let header = std::str::from_utf8(&ply[..header_end]).unwrap();
    let vertices: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .unwrap_or_else(|| panic!("no vertex element in {header}"))
        .parse()
        .unwrap();
    assert_eq!(vertices, csv_occupied.len());
    run_ok(dir, ["export", "map.bgkmap", "--format", "ply", "--out", "map.ply"]);
    assert!(std::fs::read(dir.join("map.ply")).unwrap() == ply, "--out PLY differs from stdout");

    // --box: exactly the full export's rows whose cell lies in the cells spanned by the box
    // corners (boundary cells included); a negative minimum checks hyphen values and floor().
    let (min, max) = ([-0.27, 0.47, 0.21], [1.52, 1.26, 0.88]);
    let arg = format!("{},{},{},{},{},{}", min[0], min[1], min[2], max[0], max[1], max[2]);
    let boxed = run_ok_text(dir, ["export", "map.bgkmap", "--format", "csv", "--box", &arg]);
    let lo = min.map(|v: f64| (v / 0.1).floor() as i32);
    let hi = max.map(|v: f64| (v / 0.1).floor() as i32);
    let inside = |k: [i32; 3]| (0..3).all(|i| lo[i] <= k[i] && k[i] <= hi[i]);
    let boxed_rows = parse_csv(&boxed);
    assert!(boxed_rows.len() > 10, "box export has only {} rows", boxed_rows.len());
    for (r, line) in &boxed_rows {
        for (i, c) in [r.x, r.y, r.z].into_iter().enumerate() {
            assert!(
                c >= min[i] - 0.05 - 1e-9 && c <= max[i] + 0.05 + 1e-9,
                "row {line:?} is outside the box"
            );
        }
        assert!(inside(r.key()), "row {line:?} is outside the box's cells");
    }
    let expected: Vec<&str> = rows.iter().filter(|(r, _)| inside(r.key())).map(|(_, l)| *l).collect();
    let got: Vec<&str> = boxed_rows.iter().map(|(_, l)| *l).collect();
    assert!(got == expected, "box export is not the full export restricted to the box");
    assert!(got.len() < rows.len());
    run_ok(dir, ["export", "map.bgkmap", "--format", "csv", "--box", &arg, "--out", "box.csv"]);
    assert!(std::fs::read(dir.join("box.csv")).unwrap() == boxed.as_bytes());
}

#[test]
fn eval_json_roc_and_accuracy_on_simulated_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let sim = simulate(dir, 8);
    build(dir, "map.bgkmap", &[], &sim.scans);
    build(dir, "half.bgkmap", &[], &sim.scans[..4]);

    let json = run_ok_text(dir, ["eval", "map.bgkmap", "--truth", &sim.truth, "--json"]);
    let json = json.trim();
    assert!(json.starts_with('{') && json.ends_with('}'), "not one JSON object: {json}");
    let auc = json_number(json, "auc");
    let auc_covered = json_number(json, "auc_covered");
    let queries = json_number(json, "queries");
    let occupied = json_number(json, "occupied");
    let free = json_number(json, "free");
    eprintln!("simulated, 8 scans: auc {auc}, auc_covered {auc_covered}, queries {queries}");
    // Measured: auc 0.8954, auc_covered 0.9485 (seed 0, 8 scans, default parameters).
    assert!(auc > 0.88 && auc <= 1.0, "auc {auc}");
    assert!(auc_covered > 0.93 && auc_covered <= 1.0, "auc_covered {auc_covered}");
    assert!(queries > 0.0 && queries == occupied + free, "queries {queries} ≠ {occupied} + {free}");

    // Several maps: an array of objects; fewer scans do not do better.
    let both = run_ok_text(dir, ["eval", "map.bgkmap", "half.bgkmap", "--truth", &sim.truth, "--json"]);
    let both = both.trim();
    assert!(both.starts_with('[') && both.ends_with(']'), "not a JSON array: {both}");
    assert_eq!(both.matches("\"auc\":").count(), 2, "expected two objects: {both}");
    let last = &both[both.rfind('{').unwrap()..];
    assert!(last.contains("half.bgkmap"), "objects are not in argument order: {both}");
    let half_auc = json_number(last, "auc");
    assert!(half_auc < auc, "4 scans (auc {half_auc}) should not beat 8 scans (auc {auc})");

    // --roc writes a PNG.
    let text = run_ok_text(dir, ["eval", "map.bgkmap", "--truth", &sim.truth, "--roc", "roc.png"]);
    assert!(text.contains("AUC"), "{text}");
    let png = std::fs::read(dir.join("roc.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"), "roc.png is not a PNG");
    assert!(png.len() > 1000);
}

fn check_bench(json: &str, scans: f64, threads: f64) {
    let json = json.trim();
    assert!(json.starts_with('{') && json.ends_with('}'), "not one JSON object: {json}");
    for key in ["per_scan_ms_median", "per_scan_ms_p90", "total_ms_median"] {
        let v = json_number(json, key);
        assert!(v.is_finite() && v > 0.0, "{key} = {v} in {json}");
    }
    assert_eq!(json_number(json, "scans"), scans, "{json}");
    assert_eq!(json_number(json, "repeat"), 1.0, "{json}");
    assert_eq!(json_number(json, "threads"), threads, "{json}");
    // The training points per scan: the fewest and the most bracket the mean, and the time per
    // training point is that of the scans' median order of magnitude (every scan has some).
    let (lo, mean, hi) = (
        json_number(json, "training_points_per_scan_min"),
        json_number(json, "training_points_per_scan_mean"),
        json_number(json, "training_points_per_scan_max"),
    );
    assert!(0.0 < lo && lo <= mean && mean <= hi, "{lo} ≤ {mean} ≤ {hi} in {json}");
    // The wait at the end of a pass, for the workers out of scans: within the pass, and none on
    // one worker (no other to wait for).
    let (tail, total) = (json_number(json, "tail_ms_median"), json_number(json, "total_ms_median"));
    assert!((0.0..=total).contains(&tail), "tail {tail} ms of a {total} ms pass in {json}");
    if threads == 1.0 {
        assert_eq!(tail, 0.0, "{json}");
    }
    let ns = json_number(json, "ns_per_training_point");
    let per_scan_ns = json_number(json, "per_scan_ms_median") * 1e6;
    assert!(ns > 0.0 && ns * lo <= 10.0 * per_scan_ns && ns * hi >= 0.1 * per_scan_ns, "{ns} ns in {json}");
}

#[test]
fn bench_ingest_json() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    // No scans: the built-in simulated room (12 scans).
    let json = run_ok_text(dir, ["bench", "ingest", "--repeat", "1", "--json"]);
    check_bench(&json, 12.0, 1.0);
    assert!(!json.contains("speedup_vs_one_worker"), "one worker has nothing to compare with: {json}");

    let sim = simulate(dir, 3);
    let mut args: Vec<String> =
        ["bench", "ingest", "--repeat", "1", "--threads", "2", "--json"].map(String::from).into();
    args.extend(sim.scans.iter().cloned());
    let json = run_ok_text(dir, &args);
    check_bench(&json, 3.0, 2.0);
    // Passes on one worker, interleaved with the two-worker passes, and the ratio of the medians.
    let (solo, total) =
        (json_number(&json, "one_worker_total_ms_median"), json_number(&json, "total_ms_median"));
    assert!(solo.is_finite() && solo > 0.0, "{json}");
    let speedup = json_number(&json, "speedup_vs_one_worker");
    assert!((speedup - solo / total).abs() <= 1e-9 * speedup, "{json}");
    // One-worker passes in runs of 10 by default: with one timed pass (and the warm-up), one.
    assert_eq!(json_number(&json, "one_worker_passes"), 1.0, "{json}");
    assert_eq!(json_number(&json, "alternate_every"), 10.0, "{json}");
    // Each worker's time per training point, of the workers that ran scans (with three scans
    // one of the two can be beaten to all of them): each of the order of all scans'.
    let workers: Vec<f64> = parse_json(&json)["per_worker_ns_per_training_point"]
        .as_array()
        .unwrap_or_else(|| panic!("no per-worker figures in {json}"))
        .iter()
        .map(|m| m.as_f64().expect("a number"))
        .collect();
    let ns = json_number(&json, "ns_per_training_point");
    assert!((1..=2).contains(&workers.len()), "{json}");
    assert!(workers.iter().all(|&w| w > 0.0 && w < 10.0 * ns && ns < 10.0 * w), "{json}");

    // Runs that do not divide the passes (the warm-up and 3 timed passes in runs of 2; the
    // warm-up and 4 in runs of 3): every timed pass gets its one-worker pass, the warm-up's is
    // left out as on the workers.
    for (repeat, every) in [(3, 2), (4, 3)] {
        let mut args: Vec<String> = ["bench", "ingest", "--threads", "2", "--json"].map(String::from).into();
        args.extend(
            ["--repeat", &repeat.to_string(), "--alternate-every", &every.to_string()].map(String::from),
        );
        args.extend(sim.scans.iter().cloned());
        let json = run_ok_text(dir, &args);
        assert_eq!(json_number(&json, "one_worker_passes"), repeat as f64, "{json}");
        assert_eq!(json_number(&json, "alternate_every"), every as f64, "{json}");
    }
}

/// The demo serves on free loopback ports, streams its robot over gRPC, and (with `--exit`)
/// stops; run twice, the second run finds every scan already in the map.
#[cfg(feature = "server")]
#[test]
fn demo_builds_and_evaluates() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let args = [
        "demo",
        "--dir",
        "demo",
        "--scans",
        "6",
        "--exit",
        "--grpc-listen",
        "127.0.0.1:0",
        "--http-listen",
        "127.0.0.1:0",
    ];
    let out = common::run(dir, args);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "demo failed:\n{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("AUC"), "demo output lacks AUC:\n{stdout}");
    assert!(stdout.contains("(6 applied, 0 already in the map)"), "{stdout}");
    assert!(
        stdout.contains("grpcurl -plaintext") && stdout.contains("curl -s http://127.0.0.1:"),
        "{stdout}"
    );
    let again = common::run(dir, args);
    assert!(String::from_utf8_lossy(&again.stdout).contains("(0 applied, 6 already in the map)"));
    for f in ["demo.bgkmap", "truth.bt"] {
        assert!(dir.join("demo").join(f).is_file(), "demo did not write {f}");
    }
    // The demo's map is a real map file.
    let map = bgkmap::store::load_map(&dir.join("demo/demo.bgkmap")).unwrap();
    assert!(map.cells_with_evidence() > 1000, "{} cells with evidence", map.cells_with_evidence());
}

/// A bench command's `--json` output.
fn parse_json(json: &str) -> serde_json::Value {
    serde_json::from_str(json.trim()).unwrap_or_else(|e| panic!("{e}: {json}"))
}

/// The figure at `path` (a JSON pointer) is a finite number above zero.
#[cfg(feature = "server")]
fn assert_positive(v: &serde_json::Value, path: &str) {
    let x = v.pointer(path).and_then(serde_json::Value::as_f64).unwrap_or(f64::NAN);
    assert!(x.is_finite() && x > 0.0, "{path} = {x} in {v}");
}

/// `bench scale` at a small size: every level's map gets the room's scans (its blocks are the
/// filler's plus the room's), each level's passes timed, and memory per cell for both maps.
#[test]
fn bench_scale_json() {
    let tmp = tempfile::tempdir().unwrap();
    let args =
        ["bench", "scale", "--levels", "0,300,1000", "--repeat", "2", "--outdoor-scans", "1", "--json"];
    let json = run_ok_text(tmp.path(), args);
    let v = parse_json(&json);
    let levels = v["levels"].as_array().unwrap_or_else(|| panic!("no levels in {json}"));
    assert_eq!(levels.len(), 3, "{json}");
    let room = levels[0]["blocks"].as_u64().unwrap_or(0);
    assert!(room > 100, "{json}");
    for (l, filler) in levels.iter().zip([0, 300, 1000]) {
        assert_eq!(l["filler_blocks"].as_u64(), Some(filler), "{json}");
        assert_eq!(l["blocks"].as_u64(), Some(room + filler), "{json}");
        for key in ["per_scan_ms_median", "per_scan_ms_p90", "query_points_per_s", "rays_8m_per_s"] {
            let x = l[key].as_f64().unwrap_or(f64::NAN);
            assert!(x.is_finite() && x > 0.0, "{key} in {json}");
        }
    }
    for map in ["room", "outdoor"] {
        for key in ["ram_bytes_per_allocated_cell", "disk_bytes_per_allocated_cell"] {
            let x = v["memory"][map][key].as_f64().unwrap_or(f64::NAN);
            assert!(x.is_finite() && x > 0.0, "{map} {key} in {json}");
        }
    }
}

/// `bench report` at quick sizes: every bench of a round run as a child process, twice, and a
/// row per figure with both rounds' values, their median and range, and no verdicts (quick
/// figures are not comparable with the targets).
#[cfg(feature = "server")]
#[test]
fn bench_report_json() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().to_str().unwrap();
    let out = tmp.path().join("report.json");
    let o = out.to_str().unwrap();
    let table =
        run_ok_text(tmp.path(), ["bench", "report", "--quick", "--rounds", "2", "--dir", d, "--json-out", o]);
    let json = std::fs::read_to_string(&out).unwrap();
    let v = parse_json(&json);
    // The table on standard output: a row per figure, each with its median.
    for r in v["rows"].as_array().into_iter().flatten() {
        let (figure, median) = (r["figure"].as_str().unwrap(), r["median"].as_f64().unwrap());
        let line = table.lines().find(|l| l.starts_with(&format!("| {figure} |")));
        assert!(line.is_some_and(|l| l.contains("| —")), "{figure} ({median}) in {table}");
    }
    let runs = v["runs"].as_object().unwrap_or_else(|| panic!("no runs in {json}"));
    let benches = ["sample", "sample_2w", "dense", "dense_2w", "query", "scale", "merge", "restart"];
    assert_eq!(runs.len(), benches.len(), "{json}");
    for b in benches {
        assert_eq!(runs[b].as_array().map(Vec::len), Some(2), "{b} in {json}");
    }
    assert_eq!(v["commands"].as_array().map(Vec::len), Some(benches.len()), "{json}");
    let rows = v["rows"].as_array().unwrap_or_else(|| panic!("no rows in {json}"));
    let mut targets = 0;
    for r in rows {
        let values: Vec<f64> = r["values"].as_array().unwrap().iter().filter_map(|x| x.as_f64()).collect();
        assert_eq!(values.len(), 2, "{r}");
        assert!(values.iter().all(|x| x.is_finite() && *x > 0.0), "{r}");
        let (lo, hi, med) =
            (r["min"].as_f64().unwrap(), r["max"].as_f64().unwrap(), r["median"].as_f64().unwrap());
        assert!(lo <= med && med <= hi && values.contains(&lo) && values.contains(&hi), "{r}");
        assert_eq!(r["verdict"], "—", "{r}");
        targets += usize::from(r["target"].is_string());
    }
    // The nine targets, two of them in two rows each (points in-process into a vector
    // and visited; RAM and disk), and the dense scan's raw points per second.
    assert_eq!(targets, 12, "{json}");
    // The generated maps are gone: only the report's JSON is left.
    assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 1, "files left in {d}");
}

/// `bench durable` end to end at a small size: three ingest runs against the real server
/// (acknowledged and integrated rates), then restart and merge of two generated maps.
#[cfg(feature = "server")]
#[test]
fn bench_durable_json() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let d = dir.to_str().unwrap();
    let args =
        ["bench", "durable", "--scans", "40", "--points", "400", "--blocks", "300", "--journal-scans", "20"];
    let json = run_ok_text(dir, args.iter().copied().chain(["--dir", d, "--json"]));
    let v = parse_json(&json);
    for run in ["unary", "stream", "four_streams"] {
        for rate in ["acked_per_s", "applied_per_s"] {
            assert_positive(&v, &format!("/ingest/{run}/{rate}"));
        }
    }
    assert_positive(&v, "/restart/open_s");
    let merged = v["merge"]["blocks"].as_u64().unwrap_or(0);
    assert!((300..=600).contains(&merged), "merged blocks {merged} in {json}");
    // The bench removes its data directory.
    let left: Vec<_> = std::fs::read_dir(dir).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

/// `bench query` end to end at a small size: in-process, then the real server over gRPC, HTTP
/// and zenoh, then single-point latency while scans stream in.
#[cfg(feature = "server")]
#[test]
fn bench_query_json() {
    let tmp = tempfile::tempdir().unwrap();
    let args =
        ["bench", "query", "--scans", "1", "--batch", "2000", "--latency-samples", "50", "--rays", "100"];
    let json = run_ok_text(tmp.path(), args.iter().copied().chain(["--json"]));
    let v = parse_json(&json);
    assert!(v["blocks"].as_u64().is_some_and(|b| b > 100), "{json}");
    for t in ["in_process", "grpc", "http", "zenoh"] {
        for key in ["points_per_s", "single_p99_us", "box_1m_ms_median", "rays_8m_per_s", "rays_30m_per_s"] {
            assert_positive(&v, &format!("/{t}/{key}"));
        }
        assert_eq!(v[t]["batch"].as_u64(), Some(2000), "{json}");
    }
    assert_positive(&v, "/in_process/points_visited_per_s");
    assert!(v["grpc"]["points_visited_per_s"].is_null(), "only in-process visits: {json}");
    for key in
        ["single_p99_us_under_ingest", "single_p99_us_under_room_ingest", "room_background_scans_per_s"]
    {
        assert_positive(&v, &format!("/grpc/{key}"));
    }
}
