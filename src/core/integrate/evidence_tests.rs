use super::cell_points::*;
use super::delta::*;
use super::floor::{floor_f64, floor_i32, floor_i64};
use super::kernel::KernelTable;
use super::scatter::Scatter;
use super::training::{TrainingBuilder, TrainingSet};
use crate::core::block::*;
use crate::core::key::{BLOCK_CELLS, CellKey};
use crate::core::params::MapParams;
use crate::core::posterior::{Evidence, FIXED_ONE};
use proptest::prelude::*;
use std::collections::BTreeMap;
use std::sync::Arc;

/// Cells per block row.
const ROW: usize = crate::core::key::BLOCK_EDGE as usize;

fn delta_cells(d: &ScanDelta) -> BTreeMap<CellKey, (i64, i64)> {
    let mut m = BTreeMap::new();
    for (k, b) in &d.blocks {
        for i in 0..BLOCK_CELLS {
            if b.a[i] != 0 || b.b[i] != 0 {
                m.insert(k.cell(i), (b.a[i], b.b[i]));
            }
        }
    }
    m
}

/// Every cell whose centre is within ell of some training point, by exhaustive search.
fn candidate_cells(set: &TrainingSet, geo: &PairGeometry) -> Vec<CellKey> {
    let mut out = std::collections::BTreeSet::new();
    let r = geo.ell_cells.ceil() as i32 + 1;
    for p in set.hits.iter().chain(&set.frees) {
        let c = CellKey::from_point(*p, geo.res_m).unwrap();
        for z in -r..=r {
            for y in -r..=r {
                for x in -r..=r {
                    out.insert(CellKey::new(c.x + x, c.y + y, c.z + z));
                }
            }
        }
    }
    out.into_iter().collect()
}

/// Points, origin and a geometry: resolution, kernel length and sub-cells (0 = points where
/// they are; 8 is the default; 16 and 64 exceed the precomputed windows' size for some widths).
fn random_scan() -> impl Strategy<Value = (Vec<[f32; 3]>, [f64; 3], f64, f64, u32)> {
    (
        prop::collection::vec((-4.0f32..4.0, -4.0f32..4.0, -2.0f32..2.0), 1..20),
        (-2.0f64..2.0, -2.0f64..2.0, -1.0f64..1.0),
        prop::sample::select(vec![0.1, 0.2]),
        prop::sample::select(vec![0.1, 0.2, 0.3, 0.45]),
        prop::sample::select(vec![0, 1, 2, 8, 8, 16, 64]),
    )
        .prop_map(|(pts, o, res, ell, sub)| {
            (pts.into_iter().map(|(x, y, z)| [x, y, z]).collect(), [o.0, o.1, o.2], res, ell, sub)
        })
}

/// The brute-force gather at every cell with evidence. Any cell outside the candidates is
/// farther than ell from every point, so gets 0.
fn brute_cells(set: &TrainingSet, geo: &PairGeometry, table: &KernelTable) -> BTreeMap<CellKey, (i64, i64)> {
    let mut brute = BTreeMap::new();
    for cell in candidate_cells(set, geo) {
        let (a, b) = brute_force_cell(set, cell, geo, table);
        if a != 0 || b != 0 {
            brute.insert(cell, (a, b));
        }
    }
    brute
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]
    /// The scatter equals the brute-force gather over all training points, cell by cell.
    #[test]
    fn scatter_equals_brute_force((pts, origin, res, ell, sub) in random_scan()) {
        let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, free_resolution_m: 0.3, max_range_m: 3.0, ..Default::default() };
        let set = TrainingBuilder::default().build(&pts, origin, &params);
        let geo = PairGeometry::new(res, ell, sub);
        let table = KernelTable::new();
        let fast = delta_cells(&Scatter::default().delta(&set, &geo, &table));
        prop_assert_eq!(fast, brute_cells(&set, &geo, &table));
    }

    /// The compact sub-cell points (what `delta` takes when it can) and `f64` cell points
    /// give the same bits, and so does a set the compact points cannot hold (a point
    /// 2^23 cells out).
    #[test]
    fn sub_points_and_cell_points_give_the_same_delta((pts, origin, res, ell, sub) in random_scan(), far in any::<bool>()) {
        let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, ..Default::default() };
        let mut set = TrainingBuilder::default().build(&pts, origin, &params);
        if far {
            set.frees.push([f64::from(1u32 << 23) * res, 0.0, 0.0]);
        }
        let geo = PairGeometry::new(res, ell, sub);
        let table = KernelTable::new();
        let mut labelled = Vec::new();
        labelled_cell_points(&set, &geo, &mut labelled);
        let compact = Scatter::default().delta(&set, &geo, &table);
        let cells = Scatter::default().delta_of(&labelled, &geo, &table);
        prop_assert_eq!(delta_cells(&compact), delta_cells(&cells));
    }

    /// Splitting the points across threads (partial deltas summed) gives the same bits.
    #[test]
    fn partial_deltas_sum_to_the_whole((pts, origin, res, ell, sub) in random_scan(), split in 0usize..200) {
        let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, ..Default::default() };
        let set = TrainingBuilder::default().build(&pts, origin, &params);
        let geo = PairGeometry::new(res, ell, sub);
        let table = KernelTable::new();
        let mut labelled = Vec::new();
        labelled_cell_points(&set, &geo, &mut labelled);
        let k = split.min(labelled.len());
        let whole = Scatter::default().delta_of(&labelled, &geo, &table);
        let parts = ScanDelta::sum(vec![
            Scatter::default().delta_of(&labelled[k..], &geo, &table),
            Scatter::default().delta_of(&labelled[..k], &geo, &table),
        ]);
        prop_assert_eq!(delta_cells(&whole), delta_cells(&parts));
    }
}

/// A block with random evidence: `a` only in cells `i % hit_every == 0` (none if 0).
fn random_block(seed: u64, hit_every: usize) -> Box<BlockEvidence> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut b = BlockEvidence::zeroed_wide();
    for i in 0..BLOCK_CELLS {
        let a = if hit_every > 0 && i % hit_every == 0 { rng.random_range(-1i64 << 40..1 << 40) } else { 0 };
        if rng.random_bool(0.7) {
            b.set(i, Evidence { a, b: rng.random_range(-1i64 << 40..1 << 40) });
        }
    }
    b
}

/// Every cell of a block, read one by one.
fn cell_list(b: &BlockEvidence) -> Vec<Evidence> {
    (0..BLOCK_CELLS).map(|i| b.get(i)).collect()
}

/// Narrow and wide blocks hold and add the same evidence: reads, equality, counts, every
/// sum and delta across the two layouts, widening (also of a block a snapshot shares) and
/// narrowing.
#[test]
fn narrow_and_wide_blocks_hold_and_add_alike() {
    let free = random_block(1, 0);
    assert!(free.is_wide(), "built wide");
    let narrow = BlockEvidence::narrowed(free.to_box());
    assert!(!narrow.is_wide() && narrow.data_bytes() * 2 == free.data_bytes());
    assert_eq!(cell_list(&narrow), cell_list(&free));
    assert_eq!(narrow.cells().collect::<Vec<_>>(), cell_list(&free));
    assert!(*narrow == *free, "narrow equals wide");
    assert!(*free == *narrow, "wide equals narrow");
    assert_eq!(narrow.cells_with_evidence(), free.cells_with_evidence());
    assert!(!narrow.is_empty() && BlockEvidence::zeroed().is_empty());
    for i in [0, 7, 300, BLOCK_CELLS - 1] {
        assert_eq!(*narrow.cell(i), free.get(i).b, "a narrow cell's first word is its b");
        assert_eq!(*free.cell(i), free.get(i).a, "a wide cell's first word is its a");
    }
    let hits = random_block(2, 3);
    assert!(BlockEvidence::narrowed(hits.to_box()).is_wide(), "a block with hits stays wide");
    assert!(*narrow != *hits);
    let other_free = BlockEvidence::narrowed(random_block(3, 0));
    // Sums in every layout pair that may take them, against the cell-by-cell sums.
    for (x, y) in [(&hits, &narrow), (&free, &other_free), (&narrow, &other_free), (&hits, &hits)] {
        for sign in [1, -1] {
            let want: Vec<Evidence> = cell_list(x)
                .iter()
                .zip(cell_list(y))
                .map(|(p, q)| Evidence { a: p.a + sign * q.a, b: p.b + sign * q.b })
                .collect();
            let mut got = x.to_box();
            got.add_scaled(y, sign);
            assert_eq!(cell_list(&got), want, "sign {sign}");
            assert_eq!(got.is_wide(), x.is_wide());
        }
    }
    // A narrow block widened in an Arc that a snapshot shares: the snapshot keeps its bits.
    let mut shared: Arc<BlockEvidence> = narrow.to_box().into();
    let snapshot = Arc::clone(&shared);
    BlockEvidence::make_mut(&mut shared, true).add_scaled(&hits, 1);
    assert!(shared.is_wide() && !snapshot.is_wide() && *snapshot == *narrow);
    let mut want = free.to_box();
    want.add_scaled(&hits, 1);
    assert!(*shared == *want);
    // Without hits to come, a narrow block stays narrow (copied only because it is shared).
    let mut shared: Arc<BlockEvidence> = narrow.to_box().into();
    let snapshot = Arc::clone(&shared);
    BlockEvidence::make_mut(&mut shared, false).add_scaled(&other_free, 1);
    assert!(!shared.is_wide() && *snapshot == *narrow && *shared != *narrow);
    // Deltas: b rows into a narrow block; a and b rows into a widened one.
    let mut d = DeltaBlock::zeroed();
    (d.b[9], d.b[500]) = (5, -7);
    let rows = [0, 1 << (9 / ROW) | 1 << (500 / ROW)];
    let mut n = narrow.to_box();
    n.add_delta(&d, 1, rows);
    let mut w = free.to_box();
    w.add_delta(&d, 1, rows);
    assert!(!n.is_wide() && *n == *w);
    d.a[64] = 11;
    let rows = [1 << (64 / ROW), rows[1]];
    BlockEvidence::widen_box(&mut n);
    n.add_delta(&d, -1, rows);
    w.add_delta(&d, -1, rows);
    assert!(n.is_wide() && *n == *w && n.get(64).a == -11);
}

/// A narrow block refuses hit mass rather than drop it.
#[test]
#[should_panic(expected = "hit mass set in a narrow block")]
fn a_narrow_block_refuses_hit_mass() {
    BlockEvidence::zeroed().set(3, Evidence { a: 1, b: 0 });
}

#[test]
#[should_panic(expected = "a wide block added into a narrow one")]
fn a_narrow_block_refuses_a_wide_one() {
    BlockEvidence::zeroed().add_scaled(&BlockEvidence::zeroed_wide(), 1);
}

/// Adding a training set straight into a map's blocks ([`Scatter::add_into`]) gives the bits
/// of applying its delta, on top of evidence already there, into a map whose blocks a
/// snapshot shares (which must not change) and into an edit.
fn check_add_into(set: &TrainingSet, earlier: &TrainingSet, geo: &PairGeometry) {
    use crate::core::EvidenceMap;
    let table = KernelTable::new();
    // The map's own parameters play no part in adding evidence.
    let mut base = EvidenceMap::new(MapParams::default());
    base.apply(&Scatter::default().delta(earlier, geo, &table), 1);
    let mut want = base.clone();
    want.apply(&Scatter::default().delta(set, geo, &table), 1);
    let snapshot = base.clone();
    let before = snapshot.clone();
    let mut scatter = Scatter::default();
    // Twice through one scatter: scratch space left by the first run must not leak.
    for _ in 0..2 {
        let mut got = base.clone();
        scatter.add_into(set, geo, &table, &mut got);
        assert!(crate::core::EvidenceMap::same_blocks_as(&got, &want), "straight into the map");
    }
    let mut edit = base.edit();
    scatter.add_into(set, geo, &table, &mut edit);
    let blocks = edit.finish();
    let mut edited = base.clone();
    edited.commit_edit(blocks);
    assert!(crate::core::EvidenceMap::same_blocks_as(&edited, &want), "through an edit");
    assert!(
        crate::core::EvidenceMap::same_blocks_as(&snapshot, &before),
        "a snapshot sharing the blocks is untouched"
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]
    #[test]
    fn adding_into_a_map_equals_applying_the_delta(
        (pts, origin, res, ell, sub) in random_scan(),
        (pts2, origin2, _, _, _) in random_scan(),
    ) {
        let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, free_resolution_m: 0.3, max_range_m: 3.0, ..Default::default() };
        let set = TrainingBuilder::default().build(&pts, origin, &params);
        let earlier = TrainingBuilder::default().build(&pts2, origin2, &params);
        check_add_into(&set, &earlier, &PairGeometry::new(res, ell, sub));
    }
}

/// The same for dense buckets (folded mid-bucket), far outliers (several tiles) and every
/// window width and the stencil path.
#[test]
fn adding_into_a_map_equals_applying_the_delta_at_the_edges() {
    let n = 2 * super::window::BRICK_POINTS as usize + 3;
    let hits: Vec<[f64; 3]> = (0..n).map(|i| [0.05 + (i % 7) as f64 * 0.1, 0.42, 0.37]).collect();
    let dense = TrainingSet { frees: hits[..n / 3].to_vec(), hits, ..Default::default() };
    let far = TrainingSet {
        hits: vec![[0.0, 0.0, 0.0], [5000.0, -4000.0, 3000.0]],
        frees: vec![[0.31, -0.2, 0.1]],
        ..Default::default()
    };
    for sub in [0, 8] {
        let geo = PairGeometry::new(0.1, 0.2, sub);
        check_add_into(&dense, &far, &geo);
        check_add_into(&far, &dense, &geo);
        for ell in [0.04, 0.1, 0.14, 0.2, 0.25, 0.3, 0.45] {
            check_add_into(&far, &far, &PairGeometry::new(0.1, ell, sub));
        }
    }
}

/// A bucket with many more points than a brick takes between folds (dense hits in one block,
/// several at the same spot so cells get the largest sums) still equals the brute force.
#[test]
fn dense_buckets_fold_in_time() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let n = 3 * super::window::BRICK_POINTS as usize + 5;
    let spot = |rng: &mut rand_chacha::ChaCha8Rng| std::array::from_fn(|_| rng.random_range(0.02..0.78));
    let mut hits: Vec<[f64; 3]> = (0..n).map(|_| spot(&mut rng)).collect();
    hits.extend(std::iter::repeat_n([0.45, 0.45, 0.45], n));
    let set = TrainingSet { frees: hits[..n / 2].to_vec(), hits, ..Default::default() };
    for sub in [0, 8] {
        let geo = PairGeometry::new(0.1, 0.2, sub);
        let table = KernelTable::new();
        let fast = delta_cells(&Scatter::default().delta(&set, &geo, &table));
        let brute = brute_cells(&set, &geo, &table);
        assert!(brute.values().any(|&(a, _)| a > i64::from(i32::MAX)), "sums beyond an i32 are exercised");
        assert_eq!(fast, brute, "sub-cells {sub}");
    }
}

/// A bucket with a point of each label in every cell (far more than a brick takes between
/// folds when cells repeat, none repeating) equals the brute force, with and without
/// sub-cells; so does the same with one cell holding a second hit halfway through.
#[test]
fn buckets_of_one_point_per_cell_equal_the_brute_force() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
    let sb = super::window::SB;
    let mut hits: Vec<[f64; 3]> = (0..sb * sb * sb)
        .map(|i| {
            let c = [i % sb, i / sb % sb, i / (sb * sb)];
            c.map(|v| (v as f64 + rng.random_range(0.05..0.95)) * 0.1 - 0.8)
        })
        .collect();
    let frees: Vec<[f64; 3]> = hits.iter().rev().map(|h| h.map(|v| v + 0.004)).collect();
    assert!(hits.len() > 4 * super::window::BRICK_POINTS as usize);
    let table = KernelTable::new();
    for repeat in [false, true] {
        if repeat {
            let h = hits[7];
            hits.insert(hits.len() / 2, h.map(|v| v + 0.001));
        }
        let set = TrainingSet { hits: hits.clone(), frees: frees.clone(), ..Default::default() };
        for sub in [0, 8] {
            let geo = PairGeometry::new(0.1, 0.2, sub);
            let fast = delta_cells(&Scatter::default().delta(&set, &geo, &table));
            assert_eq!(fast, brute_cells(&set, &geo, &table), "sub-cells {sub}, a repeated cell: {repeat}");
        }
    }
}

/// The float floor equals the integer one converted, at and around integers, halves and
/// the ends of the range, for both signs.
#[test]
fn float_floor_equals_the_integer_floor() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let mut vs =
        vec![0.0, -0.0, 0.5, -0.5, 1.5, -1.5, 2.5, -2.5, (1u64 << 50) as f64, -((1u64 << 50) as f64)];
    for k in -300i32..300 {
        let v = f64::from(k) * 0.5;
        vs.extend([v, v.next_up(), v.next_down()]);
    }
    vs.extend((0..10_000).map(|_| rng.random_range(-1e7..1e7)));
    vs.extend((0..10_000).map(|_| rng.random_range(-1e15..1e15)));
    for v in vs {
        assert_eq!(floor_f64(v).to_bits(), (floor_i64(v) as f64).to_bits(), "floor of {v}");
    }
}

/// Sub-cell placement keeps a point in its cell, at most 1/(2n) of a cell per axis from
/// where it was, at the centre of its sub-cell; 0 sub-cells leaves it alone.
#[test]
fn points_move_to_their_sub_cell_centres() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    for n in [1u32, 2, 8, 64] {
        let geo = PairGeometry::new(0.1, 0.2, n);
        for i in 0..10_000 {
            let p: [f64; 3] = std::array::from_fn(|_| match i % 3 {
                0 => rng.random_range(-1e4..1e4),
                1 => f64::from(rng.random_range(-1000..1000)) * 0.1 / f64::from(n),
                _ => rng.random_range(-1.0..1.0),
            });
            let raw = to_cell_units(p, &PairGeometry::new(0.1, 0.2, 0));
            let placed = to_cell_units(p, &geo);
            for a in 0..3 {
                assert_eq!(floor_i32(placed[a]), floor_i32(raw[a]), "same cell: {p:?}");
                assert!((placed[a] - raw[a]).abs() <= 0.5 / f64::from(n) + 1e-9, "{p:?}");
                let k = placed[a] * f64::from(n) - 0.5;
                assert_eq!(k, k.round(), "a sub-cell centre: {p:?}");
            }
        }
    }
    assert_eq!(
        to_cell_units([0.123, -0.05, 7.0], &PairGeometry::new(0.1, 0.2, 0)),
        [0.123 / 0.1, -0.5, 70.0]
    );
}

/// Sub-cell points hold exactly the cell units `to_cell_units` gives, hits first, for every
/// sub-cell count, both signs and points on sub-cell and cell boundaries; a set with a point
/// beyond their fixed point's range is refused (the evidence path then takes `f64` points).
#[test]
fn sub_points_are_the_cell_points_in_fixed_point() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
    for n in [1u32, 2, 4, 8, 16, 32, 64] {
        let geo = PairGeometry::new(0.1, 0.2, n);
        let mut set = TrainingSet::default();
        for i in 0..3_000 {
            let p: [f64; 3] = std::array::from_fn(|_| match i % 4 {
                0 => rng.random_range(-1e5..1e5),
                1 => f64::from(rng.random_range(-1000..1000)) * 0.1 / f64::from(n),
                2 => rng.random_range(-1.0..1.0),
                _ => f64::from(rng.random_range(-3..3)) * 0.1,
            });
            if i % 2 == 0 { set.hits.push(p) } else { set.frees.push(p) }
        }
        let (mut subs, mut cells) = (Vec::new(), Vec::new());
        assert!(labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
        labelled_cell_points(&set, &geo, &mut cells);
        assert_eq!(subs.len(), cells.len());
        for (&(q, hit), &(p, cell_hit)) in subs.iter().zip(&cells) {
            assert_eq!(hit, cell_hit);
            assert_eq!(sub_point_cell_units(q), p, "n = {n}");
        }
        // 2^23 cells (840 km at 0.1 m) is beyond the fixed point; just inside it is not.
        let edge = f64::from(1u32 << 23) * 0.1;
        set.frees.push([0.0, -(edge - 1.0), 0.0]);
        assert!(labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
        set.frees.push([0.0, 0.0, edge]);
        assert!(!labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
        // Also when the far point comes first, with whole chunks of points after it.
        set.frees.pop();
        set.hits.insert(0, [-edge, 0.0, 0.0]);
        assert!(!labelled_sub_points(&set, &geo, &mut subs), "n = {n}");
    }
}

/// The branch-free floors equal `f64::floor` at and around integers, halves and the ends of
/// their ranges, for both signs.
#[test]
fn floors_are_exact() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
    let near = |v: f64| [v, f64::from_bits(v.to_bits() + 1), f64::from_bits(v.to_bits().saturating_sub(1))];
    let mut values = vec![0.0, -0.0, f64::MIN_POSITIVE, -f64::MIN_POSITIVE, 0.5, -0.5];
    for k in [1.0, 2.0, 3.0, 7.5, 1e6, 1048576.5, 2f64.powi(30), 2f64.powi(50) + 0.5] {
        for v in near(k).into_iter().chain(near(-k)) {
            values.push(v);
        }
    }
    values.extend((0..100_000).map(|_| rng.random_range(-1e7..1e7)));
    values.extend((0..100_000).map(|_| f64::from(rng.random_range(-1000..1000)) * 0.1));
    for v in values {
        assert_eq!(floor_i64(v), v.floor() as i64, "{v:e}");
        if v.abs() < 2f64.powi(31) {
            assert_eq!(floor_i32(v), v.floor() as i32, "{v:e}");
        }
    }
}

#[test]
fn far_outliers_are_tiled_not_allocated_densely() {
    let set = TrainingSet { hits: vec![[0.0, 0.0, 0.0], [5000.0, -4000.0, 3000.0]], ..Default::default() };
    // Points where they are: a point at a cell centre stays there.
    let geo = PairGeometry::new(0.1, 0.2, 0);
    let d = Scatter::default().delta(&set, &geo, &KernelTable::new());
    let cells = delta_cells(&d);
    assert!(cells.keys().any(|c| c.x > 40000) && cells.keys().any(|c| c.x < 10));
    // One isolated point at a cell centre: 33 lattice centres within 2 cells, minus those at exactly 2.
    let set = TrainingSet { hits: vec![[0.05, 0.05, 0.05]], ..Default::default() };
    let cells = delta_cells(&Scatter::default().delta(&set, &geo, &KernelTable::new()));
    assert_eq!(cells.len(), 27, "offsets with |d|² < 4 cells²: 1 + 6 + 12 + 8");
    assert_eq!(cells[&CellKey::new(0, 0, 0)].0, FIXED_ONE as i64);
}
