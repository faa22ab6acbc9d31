//! The updates of a map: catch-up from the snapshot equals following live, lag resyncs, filters.

use super::tests::sim_scans;
use super::*;
use crate::core::{BlockKey, PointFrame, Pose};
use crate::store::ScanSelector;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll, Wake, Waker};
use std::time::Duration;

fn service(dir: &std::path::Path, updates_capacity: usize) -> MapService {
    let svc = MapService::open(dir, ServiceConfig { updates_capacity, ..Default::default() }).unwrap();
    if svc.map_info("m").is_err() {
        svc.create_map("m", MapParams::default()).unwrap();
    }
    svc
}

fn next(sub: &mut Subscription) -> Arc<MapUpdate> {
    match sub.next_timeout(Duration::from_secs(30)) {
        Some(Next::Update(u)) => u,
        other => panic!("expected an update, got {other:?}"),
    }
}

/// Block → the version of the last update that named it.
fn apply(cache: &mut BTreeMap<BlockKey, u64>, u: &MapUpdate) {
    for k in &u.blocks {
        cache.insert(*k, u.version);
    }
}

#[test]
fn a_late_subscriber_catches_up_to_what_a_watcher_saw() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 256);
    let scans = sim_scans(5);
    let (first, mut early) = svc.watch("m", Some(0), None).unwrap();
    assert_eq!((first.kind, first.version, first.blocks.len()), (UpdateKind::CatchUp, 0, 0));
    let mut watched = BTreeMap::new();
    let mut at_2 = BTreeMap::new();
    for (i, s) in scans.iter().enumerate() {
        svc.insert_scan_blocking("m", s.clone()).unwrap();
        let u = next(&mut early);
        assert_eq!((u.kind, u.from_version, u.version), (UpdateKind::Live, i as u64, i as u64 + 1));
        assert!(!u.blocks.is_empty() && u.blocks.windows(2).all(|w| w[0] < w[1]), "sorted, non-empty");
        assert_eq!(u.poses.len(), 1);
        assert_eq!((u.poses[0].seq, u.poses[0].world_from_sensor), (s.seq, s.world_from_sensor));
        apply(&mut watched, &u);
        if u.version == 2 {
            at_2 = watched.clone();
        }
    }
    let snap = svc.snapshot("m").unwrap();
    let all: Vec<BlockKey> = watched.keys().copied().collect();
    assert_eq!(all, snap.map.block_keys_sorted(), "the live updates name every block of the map");
    let late = svc.changes_since("m", 2, None).unwrap();
    let changed_after_2: Vec<BlockKey> = watched.iter().filter(|(_, v)| **v > 2).map(|(k, _)| *k).collect();
    assert_eq!(late.blocks, changed_after_2);
    assert_eq!((late.from_version, late.version), (2, 5));
    assert_eq!(late.poses.iter().map(|p| p.version).collect::<Vec<_>>(), vec![3, 4, 5]);
    // A cache built at version 2 plus the catch-up names the same blocks as the watcher's.
    let mut cache = at_2;
    apply(&mut cache, &late);
    assert_eq!(cache.keys().collect::<Vec<_>>(), watched.keys().collect::<Vec<_>>());
    assert_eq!(svc.changes_since("m", 0, None).unwrap().blocks, all);
    assert!(svc.changes_since("m", 5, None).unwrap().blocks.is_empty());
    match svc.changes_since("m", 6, None) {
        Err(ServiceError::InvalidArgument { field, .. }) => assert_eq!(field, "since_version"),
        other => panic!("{other:?}"),
    }
    assert_eq!(svc.recent_poses("m").unwrap().len(), 5);
}

#[test]
fn a_lagging_subscriber_is_resynchronised_not_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 2);
    let scans = sim_scans(6);
    svc.insert_scan_blocking("m", scans[0].clone()).unwrap();
    let (_, mut sub) = svc.watch("m", None, None).unwrap();
    assert_eq!(sub.version(), 1);
    for s in &scans[1..5] {
        svc.insert_scan_blocking("m", s.clone()).unwrap();
    }
    // Versions 2 and 3 have left the two-update ring: one resync covers 2..=5.
    let u = next(&mut sub);
    assert_eq!((u.kind, u.from_version, u.version), (UpdateKind::Resync, 1, 5));
    assert_eq!(u.blocks, svc.changes_since("m", 1, None).unwrap().blocks);
    assert_eq!(u.poses.iter().map(|p| p.version).collect::<Vec<_>>(), vec![4, 5], "poses the ring holds");
    svc.insert_scan_blocking("m", scans[5].clone()).unwrap();
    let u = next(&mut sub);
    assert_eq!((u.kind, u.version), (UpdateKind::Live, 6));
    assert!(sub.next_timeout(Duration::from_millis(10)).is_none());
}

#[test]
fn a_box_filter_keeps_only_its_blocks() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 256);
    let res = MapParams::default().resolution_m;
    let filter = BlockBox::from_world([0.0, 0.0, 0.0], [2.0, 2.0, 1.0], res).unwrap();
    let (_, mut sub) = svc.watch("m", None, Some(filter)).unwrap();
    let scan = sim_scans(1).remove(0);
    svc.insert_scan_blocking("m", scan).unwrap();
    let u = next(&mut sub);
    let everything = svc.changes_since("m", 0, None).unwrap().blocks;
    let inside: Vec<BlockKey> = everything.iter().copied().filter(|k| filter.contains(*k)).collect();
    assert!(!inside.is_empty() && inside.len() < everything.len(), "the box cuts the scan's blocks");
    assert_eq!(u.blocks, inside);
    assert_eq!(svc.changes_since("m", 0, Some(&filter)).unwrap().blocks, inside);
    assert!(BlockBox::from_world([1.0, 0.0, 0.0], [0.0, 1.0, 1.0], res).is_err());
    assert!(BlockBox::from_world([f64::NAN, 0.0, 0.0], [1.0, 1.0, 1.0], res).is_err());
}

#[derive(Default)]
struct Flag(AtomicBool);

impl Wake for Flag {
    fn wake(self: Arc<Self>) {
        self.0.store(true, Ordering::SeqCst);
    }
}

#[test]
fn polling_wakes_on_publish_and_ends_on_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 256);
    let (_, mut sub) = svc.watch("m", None, None).unwrap();
    let flag = Arc::new(Flag::default());
    let waker = Waker::from(flag.clone());
    let mut cx = Context::from_waker(&waker);
    assert!(sub.poll_next(&mut cx).is_pending());
    svc.insert_scan_blocking("m", sim_scans(1).remove(0)).unwrap();
    assert!(flag.0.load(Ordering::SeqCst), "publishing wakes the waiting subscriber");
    assert!(matches!(sub.poll_next(&mut cx), Poll::Ready(Next::Update(u)) if u.version == 1));
    assert!(sub.poll_next(&mut cx).is_pending());
    svc.close_updates();
    assert!(matches!(sub.poll_next(&mut cx), Poll::Ready(Next::Closed)));
}

/// A square patch of returns around (x, y) seen from 2 m above: blocks no simulated scan touches.
fn patch(source: &str, seq: u64, x: f32, y: f32) -> ScanInput {
    let points = (0..400).map(|i| [x + (i % 20) as f32 * 0.05, y + (i / 20) as f32 * 0.05, 0.5]).collect();
    ScanInput {
        source: source.into(),
        seq,
        world_from_sensor: Pose::at([f64::from(x) + 0.5, f64::from(y) + 0.5, 2.5]),
        frame: PointFrame::World,
        points,
        max_range_m: None,
        stamp_nanos: None,
    }
}

/// Follows `sub` up to `version`, checking the updates are contiguous; returns them.
fn follow(sub: &mut Subscription, version: u64) -> Vec<Arc<MapUpdate>> {
    let mut out: Vec<Arc<MapUpdate>> = Vec::new();
    while sub.version() < version {
        let from = sub.version();
        let u = next(sub);
        assert_eq!((u.kind, u.from_version, u.reset), (UpdateKind::Live, from, false));
        assert!(u.version > u.from_version && u.blocks.windows(2).all(|w| w[0] < w[1]));
        out.push(u);
    }
    assert_eq!(out.last().map(|u| u.version), Some(version));
    out
}

#[test]
fn batches_and_exact_operations_each_publish_the_blocks_they_changed() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 256);
    let (_, mut sub) = svc.watch("m", Some(0), None).unwrap();
    // Queued without waiting: the writer integrates them in batches (one update spans several
    // versions, with one pose per scan).
    let scans = sim_scans(8);
    for s in &scans[..7] {
        svc.submit(
            "m",
            s.clone(),
            SubmitOptions::default(),
            Box::new(|r| {
                r.unwrap();
            }),
        )
        .unwrap();
    }
    svc.insert_scan_blocking("m", scans[7].clone()).unwrap();
    svc.insert_scan_blocking("m", patch("robot2", 1, 30.0, 30.0)).unwrap();
    let mut updates = follow(&mut sub, 9);
    let poses: Vec<u64> = updates.iter().flat_map(|u| u.poses.iter().map(|p| p.version)).collect();
    assert_eq!(poses, (1..=9).collect::<Vec<_>>(), "one pose per scan, at the version it produced");
    let patch_blocks = updates.last().unwrap().blocks.clone();
    // Retract (the patch's blocks lose all evidence), re-pose, merge: one update each.
    let other = MergeSource::Map("o".into());
    svc.create_map("o", MapParams::default()).unwrap();
    svc.insert_scan_blocking("o", patch("robot3", 1, -30.0, 30.0)).unwrap();
    let retract = ScanSelector { source: Some("robot2".into()), ..Default::default() };
    let moved = Pose::at([scans[0].world_from_sensor.translation_m[0] + 0.3, 1.0, 0.5]);
    let changes = [
        svc.retract("m", retract).unwrap(),
        svc.repose("m", vec![(("robot1".into(), 1), moved)]).unwrap(),
        svc.merge("m", other).unwrap(),
    ];
    for c in changes {
        let u = follow(&mut sub, c.version).pop().unwrap();
        assert_eq!((u.from_version + 1, u.blocks.len() as u64), (c.version, c.blocks_changed));
        assert!(u.poses.is_empty());
        updates.push(u);
    }
    assert_eq!(updates[updates.len() - 3].blocks, patch_blocks, "the retraction names the emptied blocks");
    let snap = svc.snapshot("m").unwrap();
    assert!(patch_blocks.iter().all(|k| snap.map.block(*k).is_none()));
    // Following the updates gives every block the version the snapshot holds for it.
    let mut cache = BTreeMap::new();
    updates.iter().for_each(|u| apply(&mut cache, u));
    let held: BTreeMap<BlockKey, u64> = snap.block_versions.iter().map(|(k, v)| (*k, *v)).collect();
    assert_eq!(cache, held);
    for since in [0, 4, 9, 10, 11] {
        let want: Vec<BlockKey> = held.iter().filter(|(_, v)| **v > since).map(|(k, _)| *k).collect();
        assert_eq!(svc.changes_since("m", since, None).unwrap().blocks, want, "since {since}");
    }
}

#[test]
fn after_a_restart_an_older_version_gets_every_block_and_a_reset() {
    let dir = tempfile::tempdir().unwrap();
    let (before, removed) = {
        let svc = service(dir.path(), 256);
        for s in sim_scans(2) {
            svc.insert_scan_blocking("m", s).unwrap();
        }
        svc.insert_scan_blocking("m", patch("robot2", 1, 30.0, 30.0)).unwrap();
        let removed = svc.changes_since("m", 2, None).unwrap().blocks;
        svc.retract("m", ScanSelector { source: Some("robot2".into()), ..Default::default() }).unwrap();
        let u = svc.changes_since("m", 3, None).unwrap();
        assert_eq!((u.blocks.clone(), u.reset), (removed.clone(), false), "known history: a plain diff");
        (3, removed)
    };
    let svc = service(dir.path(), 256);
    let snap = svc.snapshot("m").unwrap();
    assert_eq!((snap.version, snap.history_from), (4, 4), "versions resume from the map file");
    let all = snap.map.block_keys_sorted();
    // The removed blocks are not known any more: the answer says the list is the whole map.
    let u = svc.changes_since("m", before, None).unwrap();
    assert_eq!((u.blocks.clone(), u.reset), (all.clone(), true));
    assert!(removed.iter().all(|k| !u.blocks.contains(k)));
    let (first, mut sub) = svc.watch("m", Some(1), None).unwrap();
    assert_eq!((first.kind, first.reset, first.blocks.len()), (UpdateKind::CatchUp, true, all.len()));
    let current = svc.changes_since("m", 4, None).unwrap();
    assert!(current.blocks.is_empty() && !current.reset);
    assert!(svc.recent_poses("m").unwrap().is_empty(), "poses are not stored in the map file");
    svc.insert_scan_blocking("m", patch("robot2", 2, -30.0, -30.0)).unwrap();
    let live = next(&mut sub);
    assert_eq!((live.from_version, live.version, live.reset), (4, 5, false));
    assert_eq!(svc.changes_since("m", 4, None).unwrap().blocks, live.blocks);
}
