use super::*;
use crate::core::EvidenceMap;
use crate::core::{Integrator, PointFrame, Pose};
use crate::sim::{Lidar, simulate};

/// `n` simulated room scans as source `robot1`, seq 1..=n (also used by the updates tests).
pub(super) fn sim_scans(n: usize) -> Vec<ScanInput> {
    let (_, scans) = simulate(0, n, &Lidar::default());
    scans
        .into_iter()
        .enumerate()
        .map(|(i, s)| ScanInput {
            source: "robot1".into(),
            seq: i as u64 + 1,
            world_from_sensor: Pose::at(s.origin),
            frame: PointFrame::World,
            points: s.points_world,
            max_range_m: None,
            stamp_nanos: None,
        })
        .collect()
}

fn offline(scans: &[ScanInput]) -> EvidenceMap {
    let params = MapParams::default();
    let mut map = EvidenceMap::new(params);
    let mut integ = Integrator::new(params);
    for s in scans {
        integ.integrate(&mut map, &s.points, s.world_from_sensor.translation_m, 1);
    }
    map
}

#[test]
fn ingest_equals_offline_build_and_survives_restart() {
    let dir = tempfile::tempdir().unwrap();
    let scans = sim_scans(3);
    {
        let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
        svc.create_map("demo", MapParams::default()).unwrap();
        for s in &scans {
            let ack = svc.insert_scan_blocking("demo", s.clone()).unwrap();
            assert!(ack.applied);
        }
        let snap = svc.snapshot("demo").unwrap();
        assert_eq!(snap.version, 3);
        assert!(EvidenceMap::same_blocks_as(&snap.map, &offline(&scans)));
        let info = svc.map_info("demo").unwrap();
        assert_eq!(info.sources["robot1"].applied, 3);
        assert_eq!(info.sources["robot1"].highest_seq, Some(3));
    }
    // A new service on the same directory resumes the map and still knows the scans.
    let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
    assert_eq!(svc.list_maps().len(), 1);
    let snap = svc.snapshot("demo").unwrap();
    assert_eq!(snap.version, 3);
    assert!(EvidenceMap::same_blocks_as(&snap.map, &offline(&scans)));
    let again = svc.insert_scan_blocking("demo", scans[1].clone()).unwrap();
    assert!(!again.applied, "a scan the map holds is not applied twice, across restarts");
    assert!(EvidenceMap::same_blocks_as(&svc.snapshot("demo").unwrap().map, &offline(&scans)));
    // And the file is a valid map for the offline tools.
    let path = dir.path().join("demo.bgkmap");
    svc.shutdown();
    assert!(EvidenceMap::same_blocks_as(&crate::store::load_map(&path).unwrap(), &offline(&scans)));
}

#[test]
fn duplicates_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
    svc.create_map("m", MapParams::default()).unwrap();
    let scans = sim_scans(2);
    svc.insert_scan_blocking("m", scans[0].clone()).unwrap();
    let before = svc.snapshot("m").unwrap();
    let ack = svc.insert_scan_blocking("m", scans[0].clone()).unwrap();
    assert_eq!(ack, Ack { applied: false, integrated: false, version: 1, dropped_points: 0 });
    let after = svc.snapshot("m").unwrap();
    assert!(Arc::ptr_eq(&before, &after));
    // Same seq from another source is a different scan.
    let other = ScanInput { source: "robot2".into(), ..scans[1].clone() };
    assert!(svc.insert_scan_blocking("m", other).unwrap().applied);
    assert_eq!(svc.map_info("m").unwrap().sources["robot1"].duplicates, 1);
}

#[test]
fn bad_input_is_refused_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
    svc.create_map("m", MapParams::default()).unwrap();
    let good = sim_scans(1).remove(0);
    let field = |r: Result<Ack, ServiceError>| match r {
        Err(ServiceError::InvalidArgument { field, .. }) => field,
        other => panic!("expected InvalidArgument, got {other:?}"),
    };
    let mut nan_pose = good.clone();
    nan_pose.world_from_sensor.translation_m[1] = f64::NAN;
    assert_eq!(field(svc.insert_scan_blocking("m", nan_pose)), "world_from_sensor");
    let mut skew = good.clone();
    skew.world_from_sensor.rotation_wxyz = [1.0, 1.0, 0.0, 0.0];
    assert_eq!(field(svc.insert_scan_blocking("m", skew)), "world_from_sensor");
    let empty = ScanInput { points: vec![], ..good.clone() };
    assert_eq!(field(svc.insert_scan_blocking("m", empty)), "points");
    let all_nan = ScanInput { points: vec![[f32::NAN, 0.0, 0.0]], ..good.clone() };
    assert_eq!(field(svc.insert_scan_blocking("m", all_nan)), "points");
    let no_source = ScanInput { source: String::new(), ..good.clone() };
    assert_eq!(field(svc.insert_scan_blocking("m", no_source)), "source");
    let bad_range = ScanInput { max_range_m: Some(f64::INFINITY), ..good.clone() };
    assert_eq!(field(svc.insert_scan_blocking("m", bad_range)), "max_range");
    assert!(matches!(svc.insert_scan_blocking("nope", good.clone()), Err(ServiceError::NotFound(_))));
    assert_eq!(svc.snapshot("m").unwrap().version, 0);
    assert_eq!(svc.map_info("m").unwrap().sources["robot1"].rejected, 5);
    // Map creation.
    assert!(matches!(svc.create_map("m", MapParams::default()), Err(ServiceError::AlreadyExists(_))));
    assert!(matches!(
        svc.create_map("../etc", MapParams::default()),
        Err(ServiceError::InvalidArgument { .. })
    ));
    let bad = MapParams { ell_m: f64::NAN, ..Default::default() };
    match svc.create_map("x", bad) {
        Err(ServiceError::InvalidArgument { field, .. }) => assert_eq!(field, "ell"),
        other => panic!("{other:?}"),
    }
    // Non-finite points are dropped and counted, not fatal.
    let mut some_nan = good.clone();
    some_nan.points.push([f32::NAN, 1.0, 1.0]);
    assert_eq!(svc.insert_scan_blocking("m", some_nan).unwrap().dropped_points, 1);
    assert_eq!(svc.map_info("m").unwrap().sources["robot1"].dropped_points, 1);
}

#[test]
fn rejections_before_the_map_are_counted_per_source() {
    let dir = tempfile::tempdir().unwrap();
    let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
    svc.create_map("m", MapParams::default()).unwrap();
    svc.count_rejected("m", "robot7").unwrap();
    svc.count_rejected("m", "robot7").unwrap();
    let s = &svc.map_info("m").unwrap().sources["robot7"];
    assert_eq!((s.received, s.applied, s.rejected), (0, 0, 2));
    assert!(matches!(svc.count_rejected("nope", "robot7"), Err(ServiceError::NotFound(_))));
    let long = "x".repeat(ScanLimits::default().max_source_len + 1);
    assert!(matches!(svc.count_rejected("m", &long), Err(ServiceError::InvalidArgument { .. })));
    assert!(matches!(svc.count_rejected("m", ""), Err(ServiceError::InvalidArgument { .. })));
    assert_eq!(svc.map_info("m").unwrap().sources.len(), 1);
    assert_eq!(svc.snapshot("m").unwrap().version, 0);
}

#[test]
fn sensor_frame_scans_equal_their_world_frame_twins() {
    let dir = tempfile::tempdir().unwrap();
    let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
    svc.create_map("w", MapParams::default()).unwrap();
    svc.create_map("s", MapParams::default()).unwrap();
    // The same points, expressed in a sensor frame translated by t (identity rotation, so the
    // f32 round trip is exact for these binary-fraction coordinates).
    let world = ScanInput {
        source: "r".into(),
        seq: 1,
        world_from_sensor: Pose::at([1.0, 2.0, 0.5]),
        frame: PointFrame::World,
        points: (0..400)
            .map(|i| [4.0, -1.0 + (i % 20) as f32 * 0.125, -0.5 + (i / 20) as f32 * 0.125])
            .collect(),
        max_range_m: None,
        stamp_nanos: None,
    };
    let sensor = ScanInput {
        frame: PointFrame::Sensor,
        points: world.points.iter().map(|p| [p[0] - 1.0, p[1] - 2.0, p[2] - 0.5]).collect(),
        ..world.clone()
    };
    svc.insert_scan_blocking("w", world).unwrap();
    svc.insert_scan_blocking("s", sensor).unwrap();
    assert!(EvidenceMap::same_blocks_as(&svc.snapshot("w").unwrap().map, &svc.snapshot("s").unwrap().map));
}

#[test]
fn a_full_queue_answers_busy() {
    let dir = tempfile::tempdir().unwrap();
    let config = ServiceConfig { queue_capacity: 1, ..Default::default() };
    let svc = MapService::open(dir.path(), config).unwrap();
    svc.create_map("m", MapParams::default()).unwrap();
    let scans = sim_scans(3);
    // The first scan's completion blocks the writer until we release it.
    let (release_tx, release_rx) = std::sync::mpsc::channel::<()>();
    let (started_tx, started_rx) = std::sync::mpsc::channel::<()>();
    svc.submit_scan(
        "m",
        scans[0].clone(),
        Box::new(move |_| {
            let _ = started_tx.send(());
            let _ = release_rx.recv();
        }),
    )
    .unwrap();
    started_rx.recv().unwrap();
    svc.submit_scan("m", scans[1].clone(), Box::new(|_| ())).unwrap(); // fills the queue
    match svc.submit_scan("m", scans[2].clone(), Box::new(|_| ())) {
        Err(ServiceError::Busy { retry_after_ms, .. }) => assert!(retry_after_ms > 0),
        other => panic!("expected Busy, got {other:?}"),
    }
    release_tx.send(()).unwrap();
    svc.shutdown();
    assert_eq!(svc.snapshot("m").unwrap().version, 2, "queued scans drain on shutdown");
}

/// Readers polling during ingest only ever see whole scans: every snapshot equals the offline
/// build of its first `version` scans.
#[test]
fn readers_never_see_a_partial_scan() {
    let dir = tempfile::tempdir().unwrap();
    let svc = Arc::new(MapService::open(dir.path(), ServiceConfig::default()).unwrap());
    svc.create_map("m", MapParams::default()).unwrap();
    let scans = sim_scans(5);
    let prefixes: Vec<EvidenceMap> = (0..=scans.len()).map(|k| offline(&scans[..k])).collect();
    let reader = {
        let svc = svc.clone();
        std::thread::spawn(move || {
            let mut seen = std::collections::BTreeSet::new();
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
            while std::time::Instant::now() < deadline {
                let snap = svc.snapshot("m").unwrap();
                let v = snap.version as usize;
                assert!(
                    EvidenceMap::same_blocks_as(&snap.map, &prefixes[v]),
                    "snapshot at version {v} is not a whole-scan state"
                );
                seen.insert(v);
                if v == 5 {
                    break;
                }
            }
            seen
        })
    };
    for s in &scans {
        svc.insert_scan_blocking("m", s.clone()).unwrap();
    }
    let seen = reader.join().unwrap();
    assert!(seen.contains(&5));
}

/// Per-source statistics survive a restart; gaps count missing sequence numbers.
#[test]
fn source_stats_count_gaps_and_survive_restart() {
    let dir = tempfile::tempdir().unwrap();
    let scans = sim_scans(3);
    {
        let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
        svc.create_map("m", MapParams::default()).unwrap();
        for (s, seq) in scans.iter().zip([1, 2, 5]) {
            svc.insert_scan_blocking("m", ScanInput { seq, ..s.clone() }).unwrap();
        }
        svc.insert_scan_blocking("m", ScanInput { seq: 2, ..scans[0].clone() }).unwrap();
        let st = &svc.map_info("m").unwrap().sources["robot1"];
        assert_eq!((st.received, st.applied, st.duplicates, st.highest_seq, st.gaps), (4, 3, 1, Some(5), 2));
    }
    let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
    let info = svc.map_info("m").unwrap();
    let st = &info.sources["robot1"];
    assert_eq!((st.received, st.applied, st.duplicates, st.highest_seq, st.gaps), (0, 3, 0, Some(5), 2));
    assert_eq!((info.scans, info.version, info.read_only.as_deref()), (3, 3, None));
    assert!(info.journal_bytes > 0);
}

/// A journal pruned after every scan publishes without a new version each time: the snapshot
/// readers have stays (its blocks are the map's; nothing is cloned), and every later snapshot,
/// recycled or not, is still exactly the map of its version. (Debug builds also check that the kept snapshot shares
/// every block with the writer's map.)
#[test]
fn publishes_that_do_not_move_the_version_keep_snapshots_exact() {
    let dir = tempfile::tempdir().unwrap();
    let config =
        ServiceConfig { retention: crate::store::Retention::MaxBytes(1), ..ServiceConfig::default() };
    let svc = MapService::open(dir.path(), config).unwrap();
    svc.create_map("m", MapParams::default()).unwrap();
    let scans = sim_scans(6);
    let mut held = Vec::new();
    for (i, s) in scans.iter().enumerate() {
        assert!(svc.insert_scan_blocking("m", s.clone()).unwrap().applied);
        // The scan's snapshot is published before the scan is acknowledged.
        let applied = svc.snapshot("m").unwrap();
        // The prune of this scan's raw data is published without a new version.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
        while svc.map_info("m").unwrap().sources["robot1"].pruned <= i as u64 {
            assert!(std::time::Instant::now() < deadline, "scan {} was never pruned", i + 1);
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        let snap = svc.snapshot("m").unwrap();
        assert!(Arc::ptr_eq(&snap, &applied), "the prune after scan {} replaced the snapshot", i + 1);
        assert_eq!(snap.version, i as u64 + 1);
        assert!(
            EvidenceMap::same_blocks_as(&snap.map, &offline(&scans[..=i])),
            "snapshot after scan {} and its prune",
            i + 1
        );
        if i % 2 == 0 {
            held.push(snap);
        }
    }
    // The updates name each scan's blocks once, under the scan's version.
    let update = svc.changes_since("m", 0, None).unwrap();
    assert_eq!(update.version, scans.len() as u64);
    assert_eq!(update.blocks, offline(&scans).block_keys_sorted());
    drop(held);
}

/// The writer recycles a retired snapshot into the next one, bringing its map up to date with
/// the blocks changed since: whatever snapshots readers hold meanwhile (so some recycled ones
/// are several publishes old), every snapshot is exactly the map of its version, also after a
/// retraction that removes blocks. (Debug builds also check each recycled map against the
/// writer's, block by block.)
#[test]
fn recycled_snapshots_are_the_maps_they_name() {
    let dir = tempfile::tempdir().unwrap();
    let svc = MapService::open(dir.path(), ServiceConfig::default()).unwrap();
    svc.create_map("m", MapParams::default()).unwrap();
    let scans = sim_scans(7);
    let mut held = Vec::new();
    for (i, s) in scans.iter().enumerate() {
        assert!(svc.insert_scan_blocking("m", s.clone()).unwrap().applied);
        let snap = svc.snapshot("m").unwrap();
        assert_eq!(snap.version, i as u64 + 1);
        assert!(
            EvidenceMap::same_blocks_as(&snap.map, &offline(&scans[..=i])),
            "snapshot after scan {}",
            i + 1
        );
        if i % 3 == 0 {
            held.push(snap);
        }
        if i == 4 {
            held.clear();
        }
    }
    let selector = crate::store::ScanSelector { scans: vec![("robot1".into(), 3)], ..Default::default() };
    assert_eq!(svc.retract("m", selector).unwrap().scans, 1);
    let rest: Vec<ScanInput> = scans.iter().filter(|s| s.seq != 3).cloned().collect();
    let snap = svc.snapshot("m").unwrap();
    assert!(EvidenceMap::same_blocks_as(&snap.map, &offline(&rest)), "the retraction's snapshot");
    assert!(snap.map.block_count() > 0);
    // What the updates say changed is what did: the blocks of the retracted scan.
    let before = offline(&scans);
    let update = svc.changes_since("m", 7, None).unwrap();
    let mut differ: Vec<_> = before
        .block_keys_sorted()
        .into_iter()
        .chain(snap.map.block_keys_sorted())
        .filter(|k| before.block(*k) != snap.map.block(*k))
        .collect();
    differ.sort_unstable();
    differ.dedup();
    assert_eq!(update.blocks, differ);
    drop(held);
}
