//! The durable map against clean builds: replay, retract, re-pose and merge give the bits of a
//! map built from scratch with the resulting scans; refusals change nothing.

use super::tests::cells;
use super::*;
use crate::core::{Integrator, PointFrame, Pose, RawScan};

fn scan(k: usize) -> RawScan {
    // A wall seen from a pose that moves with k, in the sensor frame.
    let points = (0..240)
        .map(|i| [2.0 + (i % 7) as f32 * 0.01, -1.2 + (i % 24) as f32 * 0.1, -0.4 + (i / 24) as f32 * 0.08])
        .collect();
    let a = 0.3 * k as f64;
    let pose = Pose {
        translation_m: [0.2 * k as f64, 0.1, 0.5],
        rotation_wxyz: [(a / 2.0).cos(), 0.0, 0.0, (a / 2.0).sin()],
    };
    RawScan { frame: PointFrame::Sensor, world_from_sensor: pose, points, max_range_m: None }
}

fn new_scan(source: &str, seq: u64, raw: RawScan) -> NewScan {
    NewScan {
        source: source.into(),
        seq,
        stamp_nanos: 1_000 * seq as i64,
        received_nanos: now_nanos(),
        scan: raw,
    }
}

fn clean(scans: &[RawScan]) -> EvidenceMap {
    let params = MapParams::default();
    let mut integ = Integrator::new(params);
    let mut map = EvidenceMap::new(params);
    for s in scans {
        map.apply(&s.delta(&mut integ, 1).unwrap(), 1);
    }
    map
}

/// Creates a map file and journals + applies `scans` as (source, seq).
fn durable(dir: &std::path::Path, name: &str, scans: &[(&str, u64, RawScan)]) -> DurableMap {
    let (mut dm, pending) = journaled(dir, name, scans, 1);
    dm.apply(&pending).unwrap();
    dm
}

/// Creates a map file (opened with `threads`) and journals `scans` as (source, seq).
fn journaled(
    dir: &std::path::Path,
    name: &str,
    scans: &[(&str, u64, RawScan)],
    threads: usize,
) -> (DurableMap, Vec<Pending>) {
    let path = dir.join(name);
    MapFile::create(&path, &MapParams::default()).unwrap().close().unwrap();
    let rec = DurableMap::open(&path, threads, Retention::All).unwrap();
    let mut file = MapFile::connect(&path).unwrap();
    let news: Vec<NewScan> = scans.iter().map(|(s, q, r)| new_scan(s, *q, r.clone())).collect();
    let entries = file.journal(&news).unwrap();
    let pending: Vec<Pending> = news
        .into_iter()
        .zip(entries)
        .map(|(n, e)| Pending { source: n.source, seq: n.seq, entry: e.unwrap(), scan: n.scan })
        .collect();
    (rec.map, pending)
}

#[test]
fn a_batch_on_several_threads_gives_the_bits_of_one_and_a_bad_scan_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let raws: Vec<RawScan> = (0..7).map(scan).collect();
    let named: Vec<(&str, u64, RawScan)> =
        raws.iter().enumerate().map(|(i, r)| ("a", i as u64 + 1, r.clone())).collect();
    for threads in [2, 3] {
        let name = format!("t{threads}.bgkmap");
        let (mut dm, pending) = journaled(dir.path(), &name, &named, threads);
        let change = dm.apply(&pending).unwrap();
        assert_eq!((change.scans, change.version), (7, 7));
        assert_eq!(cells(dm.map()), cells(&clean(&raws)), "{threads} threads");
        drop(dm);
        assert_eq!(cells(&load_map(&dir.path().join(&name)).unwrap()), cells(&clean(&raws)), "as stored");
        // One scan at a time: each lone scan is split across the threads, into the map's edit.
        let name = format!("lone{threads}.bgkmap");
        let (mut dm, pending) = journaled(dir.path(), &name, &named, threads);
        for p in &pending {
            dm.apply(std::slice::from_ref(p)).unwrap();
        }
        assert_eq!(cells(dm.map()), cells(&clean(&raws)), "{threads} threads, one scan at a time");
        drop(dm);
        assert_eq!(cells(&load_map(&dir.path().join(&name)).unwrap()), cells(&clean(&raws)), "as stored");
    }
    // A scan whose pose cannot be used, in the middle of a batch: the batch fails, nothing moves.
    let mut bad = named.clone();
    bad[3].2.world_from_sensor.rotation_wxyz = [f64::NAN, 0.0, 0.0, 0.0];
    let (mut dm, pending) = journaled(dir.path(), "bad.bgkmap", &bad, 2);
    let before = cells(dm.map());
    let err = dm.apply(&pending).unwrap_err().to_string();
    assert!(err.contains("a") && err.contains('4'), "{err}");
    assert_eq!(cells(dm.map()), before);
    assert_eq!(dm.version(), 0);
}

#[test]
fn journaled_scans_replay_on_open_and_duplicates_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    MapFile::create(&path, &MapParams::default()).unwrap().close().unwrap();
    let mut file = MapFile::connect(&path).unwrap();
    let out = file
        .journal(&[new_scan("a", 1, scan(0)), new_scan("a", 2, scan(1)), new_scan("a", 1, scan(2))])
        .unwrap();
    assert!(out[0].is_some() && out[1].is_some() && out[2].is_none(), "the second (a, 1) is a duplicate");
    drop(file); // a "crash": journaled, never applied
    assert_eq!(cells(&load_map(&path).unwrap()), cells(&clean(&[scan(0), scan(1)])), "readers replay");
    let rec = DurableMap::open(&path, 1, Retention::All).unwrap();
    assert_eq!(rec.pending.len(), 2);
    assert!(matches!(DurableMap::open(&path, 1, Retention::All), Err(StoreError::Locked { .. })));
    drop(rec);
    let dm = DurableMap::open_recovered(&path).unwrap();
    assert_eq!(cells(dm.map()), cells(&clean(&[scan(0), scan(1)])));
    assert_eq!(dm.version(), 2);
    let c = &dm.journal().content()["a"];
    assert_eq!((c.applied, c.pending, c.highest_seq, c.gaps), (2, 0, Some(2), 0));
}

#[test]
fn retract_and_repose_equal_clean_builds() {
    let dir = tempfile::tempdir().unwrap();
    let mut dm = durable(
        dir.path(),
        "m.bgkmap",
        &[("a", 1, scan(0)), ("b", 1, scan(1)), ("a", 2, scan(2)), ("b", 2, scan(3))],
    );
    let ch = dm.retract(&ScanSelector { source: Some("b".into()), ..Default::default() }).unwrap();
    assert_eq!((ch.scans, ch.version), (2, 5));
    assert_eq!(cells(dm.map()), cells(&clean(&[scan(0), scan(2)])));
    // Re-pose (a, 2) to the pose of scan 5: as if it had been sent so.
    let moved = RawScan { world_from_sensor: scan(5).world_from_sensor, ..scan(2) };
    dm.repose(&[(("a".into(), 2), moved.world_from_sensor)]).unwrap();
    assert_eq!(cells(dm.map()), cells(&clean(&[scan(0), moved.clone()])));
    // The file agrees, after reopening.
    let path = dm.path().to_path_buf();
    dm.close().unwrap();
    assert_eq!(cells(&load_map(&path).unwrap()), cells(&clean(&[scan(0), moved])));
    let mut dm = DurableMap::open_recovered(&path).unwrap();
    // A retracted scan stays known; unknown scans and empty selectors are clear errors.
    assert!(matches!(
        dm.retract(&ScanSelector { scans: vec![("b".into(), 1)], ..Default::default() }),
        Err(OpError::NotFound(_))
    ));
    assert!(matches!(dm.retract(&ScanSelector::default()), Err(OpError::Invalid(_))));
    let by_time =
        ScanSelector { from_stamp_nanos: Some(0), to_stamp_nanos: Some(1_500), ..Default::default() };
    assert_eq!(dm.retract(&by_time).unwrap().scans, 1, "stamp 1000 is (a, 1); (b, 1) is already retracted");
}

#[test]
fn merge_counts_shared_scans_once_and_refuses_what_it_cannot_do_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let shared = ("s", 7, scan(9));
    let mut a = durable(dir.path(), "a.bgkmap", &[("r1", 1, scan(1)), shared.clone()]);
    let b = durable(dir.path(), "b.bgkmap", &[("r2", 1, scan(2)), shared.clone()]);
    let b_path = b.path().to_path_buf();
    drop(b);
    let ch = a.merge_from(&b_path).unwrap();
    assert_eq!((ch.scans, ch.shared), (1, 1));
    assert_eq!(cells(a.map()), cells(&clean(&[scan(1), scan(9), scan(2)])));
    assert!(a.journal().contains("r2", 1));
    // Merging again adds nothing (everything is shared).
    a.merge_from(&b_path).unwrap();
    assert_eq!(cells(a.map()), cells(&clean(&[scan(1), scan(9), scan(2)])));
    let own = a.path().to_path_buf();
    assert!(matches!(a.merge_from(&own), Err(OpError::Invalid(_))));

    // Same identity, different content: refused, nothing changes.
    let c = durable(dir.path(), "c.bgkmap", &[("s", 7, scan(4))]);
    let c_path = c.path().to_path_buf();
    drop(c);
    let before = cells(a.map());
    let err = a.merge_from(&c_path).unwrap_err();
    assert!(
        matches!(&err, OpError::Refused(m) if m.contains("different content") && m.contains("(s, 7)")),
        "{err}"
    );
    assert_eq!(cells(a.map()), before);

    // A shared scan whose raw scan is gone from both maps cannot be subtracted.
    let mut p = durable(dir.path(), "p.bgkmap", std::slice::from_ref(&shared));
    p.set_retention(Retention::None);
    assert_eq!(p.prune(now_nanos()).unwrap(), 1);
    let mut q = durable(dir.path(), "q.bgkmap", &[shared]);
    q.set_retention(Retention::None);
    q.prune(now_nanos()).unwrap();
    let err = q.merge_from(p.path()).unwrap_err();
    assert!(matches!(&err, OpError::Refused(m) if m.contains("pruned")), "{err}");
    let err = q.retract(&ScanSelector { source: Some("s".into()), ..Default::default() }).unwrap_err();
    assert!(matches!(&err, OpError::Refused(m) if m.contains("pruned")), "{err}");
}

#[test]
fn a_full_file_fails_the_write_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    MapFile::create(&path, &MapParams::default()).unwrap().close().unwrap();
    let mut file = MapFile::connect(&path).unwrap();
    let pages: i64 = file.conn.query_row("PRAGMA page_count", [], |r| r.get(0)).unwrap();
    let page_bytes: i64 = file.conn.query_row("PRAGMA page_size", [], |r| r.get(0)).unwrap();
    file.set_max_pages(pages as u64 + 2).unwrap();
    // More records than two pages hold, whatever the page size (each record is about 1.4 KB).
    let n = (3 * page_bytes / 1024).max(8) as u64;
    let big: Vec<NewScan> = (0..n).map(|i| new_scan("a", i, scan(i as usize))).collect();
    let err = file.journal(&big).unwrap_err();
    assert!(err.to_string().contains("full"), "{err}");
    file.set_max_pages(1 << 30).unwrap();
    assert!(file.journal(&big).unwrap().iter().all(Option::is_some), "nothing of the failed batch was kept");
}

#[test]
fn retention_keeps_what_the_policy_says_and_operations_name_what_is_gone() {
    let dir = tempfile::tempdir().unwrap();
    let scans: Vec<_> = (0..4).map(|k| ("r", k as u64 + 1, scan(k))).collect();
    let mut dm = durable(dir.path(), "m.bgkmap", &scans);
    let per_scan = dm.journal().get("r", 1).unwrap().record_bytes;
    assert_eq!(
        dm.stored_bytes(),
        scans.iter().map(|(s, q, _)| dm.journal().get(s, *q).unwrap().record_bytes).sum::<u64>()
    );
    // A size limit prunes the oldest first.
    dm.set_retention("1GiB".parse().unwrap());
    assert_eq!(dm.prune(now_nanos()).unwrap(), 0);
    dm.set_retention(Retention::MaxBytes(2 * per_scan + per_scan / 2));
    assert_eq!(dm.prune(now_nanos()).unwrap(), 2);
    let status = |dm: &DurableMap, q| dm.journal().get("r", q).unwrap().status;
    assert_eq!(
        [1, 2, 3, 4].map(|q| status(&dm, q)),
        [ScanStatus::Pruned, ScanStatus::Pruned, ScanStatus::Applied, ScanStatus::Applied]
    );
    // An age limit: everything was received just now, so only a zero age prunes.
    dm.set_retention("7d".parse().unwrap());
    assert_eq!(dm.prune(now_nanos()).unwrap(), 0);
    dm.set_retention(Retention::MaxAgeSeconds(0));
    assert_eq!(dm.prune(now_nanos() + 1).unwrap(), 2);
    // The evidence is untouched; operations that need raw scans say they are gone.
    assert_eq!(cells(dm.map()), cells(&clean(&[scan(0), scan(1), scan(2), scan(3)])));
    let err = dm.repose(&[(("r".into(), 3), Pose::at([0.0, 0.0, 0.5]))]).unwrap_err();
    assert!(matches!(&err, OpError::Refused(m) if m.contains("(r, 3)") && m.contains("pruned")), "{err}");
    assert!(check::check_map(dm.path()).unwrap().is_ok());
    for bad in ["", "7 weeks", "-1d", "xMB", "1e400GB"] {
        assert!(bad.parse::<Retention>().is_err(), "{bad:?}");
    }
    assert_eq!("none".parse::<Retention>(), Ok(Retention::None));
    assert_eq!("12h".parse::<Retention>(), Ok(Retention::MaxAgeSeconds(43_200)));
    assert_eq!("2MiB".parse::<Retention>(), Ok(Retention::MaxBytes(2 << 20)));
}
