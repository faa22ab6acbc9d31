//! The change feed: catch-up from the snapshot equals following live, lag resyncs, filters.

use super::*;
use crate::core::{BlockKey, PointFrame, Pose};
use crate::sim::{Lidar, simulate};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll, Wake, Waker};
use std::time::Duration;

fn sim_scans(n: usize) -> Vec<ScanInput> {
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
        })
        .collect()
}

fn service(dir: &std::path::Path, feed_capacity: usize) -> MapService {
    let svc = MapService::open(dir, ServiceConfig { feed_capacity, ..Default::default() }).unwrap();
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
    svc.close_feeds();
    assert!(matches!(sub.poll_next(&mut cx), Poll::Ready(Next::Closed)));
}

#[test]
fn after_a_restart_every_block_counts_as_changed_at_the_loaded_version() {
    let dir = tempfile::tempdir().unwrap();
    {
        let svc = service(dir.path(), 256);
        for s in sim_scans(2) {
            svc.insert_scan_blocking("m", s).unwrap();
        }
    }
    let svc = service(dir.path(), 256);
    let all = svc.snapshot("m").unwrap().map.block_keys_sorted();
    assert_eq!(svc.changes_since("m", 1, None).unwrap().blocks, all, "a superset is safe for caches");
    assert!(svc.changes_since("m", 2, None).unwrap().blocks.is_empty());
    assert!(svc.recent_poses("m").unwrap().is_empty(), "poses are not stored in the map file");
}
