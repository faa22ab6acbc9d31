//! The map file format is a public API: `tests/fixtures/format-v2.bgkmap` and `format-v3.bgkmap`
//! were written by those format versions and must keep opening with the same content (a version
//! 2 file is upgraded to 3 when opened for writing). Each holds every journal state:
//! `(a, 1)` applied, `(a, 2)` retracted, `(b, 1)` applied with its raw scan pruned, `(b, 2)`
//! journaled but not applied (a crash before integration), so its evidence comes from replay.
//!
//! Regenerate (only when introducing a new format version, as a new fixture file):
//! `BGKMAP_WRITE_FIXTURE=1 cargo test --test integration format_fixture -- --ignored`.
#![allow(clippy::unwrap_used)]

use bgkmap::core::{EvidenceMap, Integrator, MapParams, PointFrame, Pose, RawScan};
use bgkmap::store::record::fingerprint;
use bgkmap::store::{
    Commit, DurableMap, FORMAT_VERSION, MapFile, NewScan, OLDEST_FORMAT_VERSION, Pending, Retention, SCHEMA,
    ScanStatus, check, load_map, load_params,
};
use std::path::{Path, PathBuf};

/// The fixture of format `version`.
fn fixture(version: i64) -> PathBuf {
    PathBuf::from(format!("{}/tests/fixtures/format-v{version}.bgkmap", env!("CARGO_MANIFEST_DIR")))
}

/// The fixtures' parameters. Version 2's predates `sub_cells`, so it reads back with `sub_cells = 0`
/// (training points where they are), which is what built its evidence.
fn params() -> MapParams {
    MapParams { max_range_m: 5.0, ell_m: 0.25, sub_cells: 0, ..MapParams::default() }
}

/// The four scans, from closed-form geometry (no simulator, so they never change).
fn scans() -> [(&'static str, u64, RawScan); 4] {
    let wall = |x: f32, n: usize| -> Vec<[f32; 3]> {
        (0..n)
            .map(|i| [x + (i % 3) as f32 * 0.02, -0.8 + (i % 17) as f32 * 0.1, -0.3 + (i / 17) as f32 * 0.1])
            .collect()
    };
    let yaw = |a: f64| [(a / 2.0).cos(), 0.0, 0.0, (a / 2.0).sin()];
    let raw = |frame, t: [f64; 3], q: [f64; 4], points, max_range_m| RawScan {
        frame,
        world_from_sensor: Pose { translation_m: t, rotation_wxyz: q },
        points,
        max_range_m,
    };
    [
        ("a", 1, raw(PointFrame::Sensor, [0.5, 0.25, 0.5], yaw(0.3), wall(2.0, 102), None)),
        ("a", 2, raw(PointFrame::World, [0.0, 0.0, 0.5], yaw(0.0), wall(1.5, 68), None)),
        ("b", 1, raw(PointFrame::World, [0.25, -0.5, 0.5], yaw(-0.2), wall(2.5, 85), Some(3.0))),
        ("b", 2, raw(PointFrame::Sensor, [-0.5, 0.0, 0.25], yaw(1.0), wall(1.8, 51), None)),
    ]
}

fn new(s: &(&str, u64, RawScan), stamp: i64) -> NewScan {
    NewScan { source: s.0.into(), seq: s.1, stamp_nanos: stamp, received_nanos: stamp, scan: s.2.clone() }
}

fn copy_of_fixture(dir: &Path, version: i64) -> PathBuf {
    let p = dir.join("fixture.bgkmap");
    std::fs::copy(fixture(version), &p).unwrap();
    p
}

/// `application_id`, `user_version` and `meta.format_version` of the file at `path`.
fn header(path: &Path) -> (i64, i64, String) {
    let c = rusqlite::Connection::open(path).unwrap();
    c.query_row(
        "SELECT *, (SELECT value FROM meta WHERE key = 'format_version') FROM pragma_application_id, pragma_user_version",
        [],
        |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)),
    )
    .unwrap()
}

#[test]
fn the_version_2_fixture_opens_with_its_content_and_is_upgraded_for_writing() {
    assert_eq!((OLDEST_FORMAT_VERSION, FORMAT_VERSION), (2, 3));
    fixture_opens_with_its_content(2);
}

#[test]
fn the_version_3_fixture_opens_with_its_content() {
    fixture_opens_with_its_content(3);
    // Both block encodings: blocks with hit mass (1) and free space (2).
    let c = rusqlite::Connection::open(fixture(3)).unwrap();
    let encodings: Vec<i64> = c
        .prepare("SELECT DISTINCT unicode(CAST(substr(data, 1, 1) AS TEXT)) FROM blocks ORDER BY 1")
        .unwrap()
        .query_map([], |r| r.get(0))
        .unwrap()
        .map(Result::unwrap)
        .collect();
    assert_eq!(encodings, [1, 2]);
}

fn fixture_opens_with_its_content(version: i64) {
    let tmp = tempfile::tempdir().unwrap();
    let path = copy_of_fixture(tmp.path(), version);
    let c = rusqlite::Connection::open(&path).unwrap();
    assert_eq!(header(&path), (0x4247_4B4D, version, version.to_string()));
    let mut stmt = c.prepare("SELECT sql FROM sqlite_master WHERE type = 'table' ORDER BY rowid").unwrap();
    let sqls: Vec<String> = stmt.query_map([], |r| r.get(0)).unwrap().map(Result::unwrap).collect();
    assert_eq!(sqls, SCHEMA);
    // Record (a, 1), byte by byte: encoding 1, sensor frame, a points codec, no max range, the
    // pose as f64 LE, 102 points.
    let rec: Vec<u8> = c
        .query_row(
            "SELECT record FROM scan_records JOIN scans USING (id) WHERE source = 'a' AND seq = 1",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(rec[..2], [1, 1]);
    assert!(rec[2] <= 1 && rec[3] == 0);
    assert_eq!(rec[4..12], 0.5f64.to_le_bytes());
    assert_eq!(rec[68..72], 102u32.to_le_bytes());
    drop(stmt);
    drop(c);

    assert_eq!(load_params(&path).unwrap(), params());
    let [a1, a2, b1, b2] = scans();
    let mut integ = Integrator::new(params());
    let mut expected = EvidenceMap::new(params());
    for s in [&a1, &b1, &b2] {
        expected.apply(&s.2.delta(&mut integ, 1).unwrap(), 1);
    }
    let loaded = load_map(&path).unwrap();
    assert!(expected.block_count() > 10);
    assert_eq!(loaded.block_keys_sorted(), expected.block_keys_sorted());
    for k in expected.block_keys_sorted() {
        assert_eq!(loaded.block(k), expected.block(k), "block {k:?}");
    }
    let report = check::check_map(&path).unwrap();
    assert!(report.is_ok(), "{report:?}");
    assert_eq!(header(&path).1, version, "reading changes no file");
    let dm = DurableMap::open_recovered(&path).unwrap();
    assert_eq!(
        header(&path),
        (0x4247_4B4D, FORMAT_VERSION, FORMAT_VERSION.to_string()),
        "opened for writing"
    );
    let j = dm.journal();
    let status = |s: &str, q| j.get(s, q).unwrap().status;
    assert_eq!(
        [status("a", 1), status("a", 2), status("b", 1), status("b", 2)],
        [ScanStatus::Applied, ScanStatus::Retracted, ScanStatus::Pruned, ScanStatus::Applied]
    );
    assert_eq!(j.get("a", 1).unwrap().crc32, fingerprint("a", 1, &a1.2));
    assert_eq!(j.get("b", 1).unwrap().crc32, fingerprint("b", 1, &b1.2), "kept after pruning");
    assert_eq!(j.get("a", 2).unwrap().stamp_nanos, 2_000);
    assert_eq!(dm.version(), 5, "3 scans applied, 1 retraction, then (b, 2) replayed");
    assert_eq!(a2.1, 2);
}

#[test]
#[ignore = "writes the fixture; run only for a new format version"]
fn write_fixture() {
    if std::env::var_os("BGKMAP_WRITE_FIXTURE").is_none() {
        return;
    }
    let path = fixture(FORMAT_VERSION);
    let _ = std::fs::remove_file(&path);
    MapFile::create(&path, &params()).unwrap().close().unwrap();
    let [a1, a2, b1, b2] = scans();
    {
        let mut dm = DurableMap::open(&path, 1, Retention::All).unwrap().map;
        let mut j = MapFile::connect(&path).unwrap();
        let rows = [new(&a1, 1_000), new(&a2, 2_000), new(&b1, 3_000)];
        let entries = j.journal(&rows).unwrap();
        let pending: Vec<Pending> = rows
            .into_iter()
            .zip(entries)
            .map(|(n, e)| Pending { source: n.source, seq: n.seq, entry: e.unwrap(), scan: n.scan })
            .collect();
        dm.apply(&pending).unwrap();
        dm.retract(&bgkmap::store::ScanSelector { scans: vec![("a".into(), 2)], ..Default::default() })
            .unwrap();
        let b1_id = dm.journal().get("b", 1).unwrap().id;
        j.commit(&Commit {
            status: vec![(b1_id, ScanStatus::Pruned)],
            version: dm.version(),
            ..Default::default()
        })
        .unwrap();
        j.journal(&[new(&b2, 4_000)]).unwrap();
        j.close().unwrap();
        dm.close().unwrap();
    }
    let c = rusqlite::Connection::open(&path).unwrap();
    c.execute_batch("PRAGMA journal_mode = DELETE; VACUUM;").unwrap();
    drop(c);
    let _ = std::fs::remove_file(bgkmap::store::lock::lock_path(&path));
}
