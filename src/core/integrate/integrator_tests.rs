use super::*;
use crate::core::block::BlockEvidence;
use crate::core::integrate::kernel::unit_kernel;
use crate::core::key::{BlockKey, CellKey};
use crate::core::params::Thresholds;
use crate::core::posterior::{CellEstimate, CellState, Evidence};

fn wall_scan() -> (Vec<[f32; 3]>, [f64; 3]) {
    // A 2 m × 2 m wall at x = 3, sampled every 2 cm, seen from the origin.
    let mut pts = Vec::new();
    for i in 0..100 {
        for j in 0..100 {
            pts.push([3.0, -1.0 + i as f32 * 0.02, -1.0 + j as f32 * 0.02]);
        }
    }
    (pts, [0.05, 0.05, 0.05])
}

#[test]
fn zeroed_blocks_are_empty_in_either_layout() {
    // Dirty chunks of about a block's size first, so some blocks come from memory the
    // allocator reuses rather than from fresh pages.
    for wide in [false, true] {
        let bytes = (8 * crate::core::key::BLOCK_CELLS) << usize::from(wide);
        let dirty: Vec<_> = (0..8).map(|_| vec![0xA5u8; bytes + 16]).collect();
        drop(dirty);
        for _ in 0..8 {
            let b = BlockEvidence::zeroed_arc(wide);
            assert_eq!((b.is_wide(), b.data_bytes()), (wide, bytes));
            assert!(b.is_empty() && b.cells().all(|e| e.is_empty()));
        }
    }
}

/// Blocks no hit reaches are kept narrow (half the bytes), through both evidence paths and
/// a snapshot; the map answers the same either way.
#[test]
fn blocks_without_hit_mass_are_narrow() {
    let params = MapParams::default();
    let (pts, o) = wall_scan();
    let mut map = EvidenceMap::new(params);
    let mut integ = Integrator::new(params);
    integ.integrate(&mut map, &pts, o, 1);
    let no_hits = |b: &BlockEvidence| b.cells().all(|e| e.a == 0);
    let count = |m: &EvidenceMap, f: &dyn Fn(&BlockEvidence) -> bool| {
        m.blocks_unsorted().filter(|(_, b)| f(b)).count()
    };
    let (narrow, without_hits) = (count(&map, &|b| !b.is_wide()), count(&map, &no_hits));
    // The free space between the sensor and the wall: most blocks. A block that only a
    // hit window's margin reached may be wide with no hit mass (rounded to 0), not more.
    assert!(narrow > map.block_count() / 2, "{narrow} narrow of {}", map.block_count());
    assert!(narrow * 10 >= without_hits * 9, "{narrow} narrow of {without_hits} without hits");
    // The same scan's delta applied (the general path) widens no block without hit mass,
    // and gives the same cells.
    let mut applied = EvidenceMap::new(params);
    let delta = integ.scan_delta(&pts, o, 1);
    applied.apply(&delta, 1);
    assert!(applied.same_blocks_as(&map));
    assert_eq!(count(&applied, &|b| !b.is_wide()), without_hits);
    // Hits into narrow blocks a snapshot shares: widened copies, the snapshot untouched.
    let snapshot = map.clone();
    let before = snapshot.clone();
    let closer: Vec<[f32; 3]> = pts.iter().map(|p| [1.5, p[1], p[2]]).collect();
    integ.integrate(&mut map, &closer, o, 2);
    assert!(snapshot.same_blocks_as(&before));
    let mut want = before.clone();
    want.apply(&integ.scan_delta(&closer, o, 1), 1);
    assert!(map.same_blocks_as(&want));
    let widened = snapshot
        .blocks_unsorted()
        .filter(|(k, b)| !b.is_wide() && map.block(**k).is_some_and(|m| m.is_wide()))
        .count();
    assert!(widened > 0, "the second wall lies in blocks the first scan left narrow");
}

#[test]
fn cells_far_from_training_data_answer_the_prior() {
    let params = MapParams::default();
    let mut map = EvidenceMap::new(params);
    let (pts, o) = wall_scan();
    Integrator::new(params).integrate(&mut map, &pts, o, 1);
    let th = Thresholds::default();
    for cell in [CellKey::new(100, 100, 100), CellKey::new(30, 0, 20), CellKey::new(-40, 0, 0)] {
        let e = map.estimate(cell, &th);
        assert!(e.evidence.is_empty());
        assert_eq!(e.probability, 0.5);
        assert!((e.variance - 0.2495).abs() < 1e-4, "prior variance α0β0/((α0+β0)²(α0+β0+1))");
        assert_eq!(e.state, CellState::Unknown);
    }
}

/// Eq. 8 over the training points where the map holds them: at sub-cell centres by default,
/// exactly where they are with `sub_cells = 0`.
#[test]
fn well_observed_cells_follow_nadaraya_watson() {
    for sub_cells in [8, 0] {
        let params = MapParams { sub_cells, ..MapParams::default() };
        let mut map = EvidenceMap::new(params);
        let (pts, o) = wall_scan();
        let mut integ = Integrator::new(params);
        integ.integrate(&mut map, &pts, o, 1);
        let set = integ.training(&pts, o).clone();
        let geo = PairGeometry::of(&params);
        let placed = |pts: &[[f64; 3]]| -> Vec<[f64; 3]> {
            pts.iter().map(|&p| crate::core::integrate::cell_points::to_cell_units(p, &geo)).collect()
        };
        let (hits, frees) = (placed(&set.hits), placed(&set.frees));
        let mut checked = 0;
        let keys = map.block_keys_sorted();
        let cells = keys.iter().flat_map(|k| (0..crate::core::key::BLOCK_CELLS).map(move |i| k.cell(i)));
        for cell in cells {
            // In cell units: the centre of cell i is i + ½.
            let c = [cell.x, cell.y, cell.z].map(|v| f64::from(v) + 0.5);
            let dist =
                |p: &[f64; 3]| ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt();
            let y: f64 = hits.iter().map(|p| unit_kernel(dist(p), geo.ell_cells)).sum();
            let k: f64 = y + frees.iter().map(|p| unit_kernel(dist(p), geo.ell_cells)).sum::<f64>();
            // Eq. 8 holds where the evidence dwarfs the priors (α0 + β0 = 0.002).
            if k < 1.0 {
                continue;
            }
            let p = map.estimate(cell, &Thresholds::default()).probability;
            assert!((p - y / k).abs() < 1e-3, "cell {cell:?}: p {p} vs Nadaraya–Watson {}", y / k);
            checked += 1;
        }
        assert!(checked > 500, "only {checked} well-observed cells");
        assert_eq!(map.estimate(CellKey::new(30, 0, 0), &Thresholds::default()).state, CellState::Occupied);
        assert_eq!(map.estimate(CellKey::new(15, 0, 0), &Thresholds::default()).state, CellState::Free);
    }
}

/// Station keeping: N insertions of one scan give exactly N times its evidence.
#[test]
fn repeated_scan_multiplies_evidence_exactly_and_removal_restores() {
    let params = MapParams::default();
    let (pts, o) = wall_scan();
    let mut integ = Integrator::new(params);
    let delta = integ.scan_delta(&pts, o, 1);
    let mut map = EvidenceMap::new(params);
    for _ in 0..15 {
        map.apply(&delta, 1);
    }
    for (key, d) in &delta.blocks {
        let b = map.block(*key).unwrap();
        for i in 0..crate::core::key::BLOCK_CELLS {
            assert_eq!((b.get(i).a, b.get(i).b), (15 * d.a[i], 15 * d.b[i]));
        }
    }
    for _ in 0..15 {
        map.apply(&delta, -1);
    }
    assert_eq!(map.block_count(), 0, "removing every insertion restores the empty map");
}

/// Every way of changing a map notes the blocks it changed: after each, the keys whose
/// blocks differ from a clone taken before are among those `take_changes` lists.
#[test]
fn the_change_log_names_every_changed_block() {
    let params = MapParams::default();
    let (pts, o) = wall_scan();
    let mut integ = Integrator::new(params);
    let mut map = EvidenceMap::new(params);
    assert_eq!(map.take_changes(), None, "a new map's history is unknown");
    let delta = integ.scan_delta(&pts, [o[0], o[1] + 0.5, o[2]], 1);
    let mut other = EvidenceMap::new(params);
    integ.integrate(&mut other, &pts, [o[0] + 0.3, o[1], o[2]], 1);
    type Step<'a> = (&'static str, Box<dyn Fn(&mut EvidenceMap) + 'a>);
    let steps: Vec<Step> = vec![
        ("integrate", Box::new(|m| Integrator::new(params).integrate(m, &pts, o, 1))),
        (
            "integrate on 3 threads",
            Box::new(|m| Integrator::new(params).integrate(m, &pts, [o[0], o[1], 0.4], 3)),
        ),
        ("apply", Box::new(|m| m.apply(&delta, 1))),
        ("remove", Box::new(|m| m.apply(&delta, -1))),
        ("merge", Box::new(|m| m.merge_from(&other).unwrap())),
        (
            "edit",
            Box::new(|m| {
                let blocks = m.blocks_after(&delta, 1);
                m.set_blocks(blocks);
            }),
        ),
        (
            "insert",
            Box::new(|m| {
                m.insert_block(BlockKey::new(50, 0, 0), m.block(m.block_keys_sorted()[0]).unwrap().to_box())
            }),
        ),
        ("empty", Box::new(|m| m.insert_block(BlockKey::new(50, 0, 0), BlockEvidence::zeroed()))),
    ];
    for (what, step) in &steps {
        let before = map.clone();
        step(&mut map);
        let noted = map.take_changes().expect("the log is complete after a take");
        let keys: std::collections::BTreeSet<BlockKey> =
            before.block_keys_sorted().into_iter().chain(map.block_keys_sorted()).collect();
        let changed: Vec<BlockKey> = keys.into_iter().filter(|k| before.block(*k) != map.block(*k)).collect();
        assert!(!changed.is_empty(), "{what} changed something");
        for k in &changed {
            assert!(noted.binary_search(k).is_ok(), "{what} changed {k:?} without noting it");
        }
        let mut copy = before.clone();
        copy.copy_blocks_from(&map, &noted);
        assert!(copy.shares_blocks_with(&map), "{what}: the noted blocks bring a copy up to date");
    }
}

#[test]
fn threads_do_not_change_the_bits() {
    let params = MapParams::default();
    let (pts, o) = wall_scan();
    let mut integ = Integrator::new(params);
    assert_eq!(integ.scan_delta(&pts, o, 1), integ.scan_delta(&pts, o, 2));
    assert_eq!(integ.scan_delta(&pts, o, 1), integ.scan_delta(&pts, o, 5));
}

/// A scan split across threads (slabs of blocks, the first straight into the map, the others
/// through maps of their own) adds the same bits as one thread, scan after scan on a map that
/// already holds the blocks, and leaves a snapshot taken between scans as it was.
#[test]
fn threads_per_scan_add_the_same_bits_into_the_map() {
    let params = MapParams::default();
    let (_, sim) = crate::sim::simulate(3, 6, &crate::sim::Lidar::default());
    let mut scans: Vec<(Vec<[f32; 3]>, [f64; 3])> =
        sim.into_iter().map(|s| (s.points_world, s.origin)).collect();
    scans.push(wall_scan());
    let build = |threads: usize, upto: usize| {
        let (mut map, mut integ) = (EvidenceMap::new(params), Integrator::new(params));
        for (pts, o) in &scans[..upto] {
            integ.integrate(&mut map, pts, *o, threads);
        }
        map
    };
    let one = build(1, scans.len());
    for threads in [2, 3, 8] {
        let (mut map, mut integ) = (EvidenceMap::new(params), Integrator::new(params));
        let mut held = Vec::new();
        for (i, (pts, o)) in scans.iter().enumerate() {
            integ.integrate(&mut map, pts, *o, threads);
            held.push(map.clone());
            assert_eq!(map.take_changes().is_some(), i > 0, "the log is complete after the first take");
        }
        assert!(EvidenceMap::same_blocks_as(&map, &one), "{threads} threads");
        for (i, snap) in held.iter().enumerate().step_by(3) {
            assert!(
                snap.same_blocks_as(&build(1, i + 1)),
                "{threads} threads: snapshot after scan {}",
                i + 1
            );
        }
    }
}

#[test]
fn slabs_split_points_by_block_column_into_even_parts() {
    let mut slabs = Vec::new();
    // Columns of very different weight: 1000 points in block column 0, 10 in each of 1..=40.
    let mut pts: Vec<CellPoint> = (0..1000).map(|i| ([0.5 + (i % 8) as f64, 3.0, 1.0], true)).collect();
    pts.extend((0..400).map(|i| ([8.0 * (1 + i % 40) as f64 + 0.5, 0.0, 0.0], i % 2 == 0)));
    for n in [1, 2, 3, 7] {
        slabs_by_block_x(&pts, n, &mut slabs);
        assert_eq!(slabs.len(), n);
        assert_eq!(slabs.iter().map(Vec::len).sum::<usize>(), pts.len());
        let column = |p: &[f64; 3]| (p[0] as i32) >> crate::core::key::BLOCK_SHIFT;
        let mut last = i32::MIN;
        for slab in slabs.iter().filter(|s| !s.is_empty()) {
            let (lo, hi) = (
                slab.iter().map(|(p, _)| column(p)).min().unwrap(),
                slab.iter().map(|(p, _)| column(p)).max().unwrap(),
            );
            assert!(lo > last, "slabs of {n} overlap or are out of order");
            last = hi;
        }
        // Each slab past the heavy first column holds at most its share plus one column.
        for slab in slabs.iter().skip(1) {
            assert!(
                slab.len() <= pts.len() / n + 10,
                "{n} slabs: {:?}",
                slabs.iter().map(Vec::len).collect::<Vec<_>>()
            );
        }
    }
    slabs_by_block_x(&[], 3, &mut slabs);
    assert!(slabs.iter().all(Vec::is_empty));
}

#[test]
fn merge_refuses_different_parameters() {
    let a = EvidenceMap::new(MapParams::default());
    let mut b = EvidenceMap::new(MapParams { ell_m: 0.3, ..Default::default() });
    let err = b.merge_from(&a).unwrap_err();
    assert!(err[0].starts_with("ell"), "{err:?}");
}

#[test]
fn log_odds_is_logit_of_probability() {
    let params = MapParams::default();
    let e = CellEstimate::from_evidence(Evidence { a: 3 << 24, b: 1 << 24 }, &params, &Thresholds::default());
    let p = e.probability;
    assert!((e.log_odds(&params) - (p / (1.0 - p)).ln()).abs() < 1e-12);
}
