use super::*;

/// Emptying a table of tagged slots moves its tag on, and when the tags come round the
/// slots are emptied for real: a voxel written 2^32 generations back is not found again.
#[test]
fn tags_coming_round_empty_the_table() {
    let inv_ds = 10.0;
    let (p, q) = ([0.05, 0.05, 0.05], [0.35, 0.05, 0.05]);
    let mut table = VoxelCentroids::<Slot>::default();
    let centroids = |table: &VoxelCentroids<Slot>| {
        let mut out = Vec::new();
        table.centroids_into(&mut out);
        out
    };
    table.add_all::<true>(&[p], inv_ds);
    assert_eq!(centroids(&table), vec![p]);
    // An ordinary generation later: p's slot is stale, q then p are two new voxels.
    table.clear();
    assert_eq!(table.tag, 2);
    table.add_all::<true>(&[q, p], inv_ds);
    assert_eq!(centroids(&table), vec![q, p]);
    // The last tag before they come round: p's slot was written with tag 2, which the tag
    // after the wrap would take for a full slot if the slots were not emptied.
    table.tag = u32::MAX;
    table.clear();
    table.clear();
    assert_eq!(table.tag, 2);
    table.add_all::<true>(&[q, p], inv_ds);
    assert_eq!(centroids(&table), vec![q, p], "a slot of an old generation was taken as full");
}

/// The batched, prefetching table equals a plain map from voxel to sum, bit for bit and in
/// first-occurrence order, across table growth and with points it must reject.
#[test]
fn voxel_table_equals_a_plain_map() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let inv_ds = 10.0;
    let mut table = VoxelCentroids::<Slot>::default();
    let mut compact = VoxelCentroids::<CompactSlot>::default();
    for round in 0..4 {
        // Clustered points (many per voxel) and scattered ones (a new voxel each), so the
        // table grows several times within one call, past the size where rounds get
        // longer (`LARGE_TABLE_BYTES`); then fewer, into that large table, so that the last
        // clear walks the occupied slots instead of emptying the whole table.
        let n = [500, 100_000, 30_000, 200][round];
        assert_eq!(table.is_large(), round >= 2, "round {round} on a large table");
        let pts: Vec<[f64; 3]> = (0..n)
            .map(|i| match i % 97 {
                0 => [f64::NAN, 0.0, 0.0],
                1 => [2e5, 0.0, 0.0],
                // At and around the ends of the key range, on each axis, and an infinity.
                3 => [0.0, -KEY_LIMIT / inv_ds, 1.0],
                4 => [0.0, 1.0, (KEY_LIMIT / inv_ds).next_down()],
                5 => [KEY_LIMIT / inv_ds, 0.0, 0.0],
                6 => [0.0, 0.0, f64::NEG_INFINITY],
                // A voxel of its own whose points have negative zeros: its centroid keeps
                // their signs.
                2 if round == 1 => [-0.0, -0.0, 500.05],
                _ if i % 3 == 0 => [0.0; 3].map(|_| rng.random_range(-1.0..1.0)),
                _ => [0.0; 3].map(|_| rng.random_range(-300.0..300.0)),
            })
            .collect();
        table.clear();
        let rejected = table.add_all::<true>(&pts, inv_ds);
        let mut order = Vec::new();
        let mut sums = std::collections::HashMap::<u64, ([f64; 3], u32)>::new();
        let mut want_rejected = 0;
        for p in &pts {
            let Some(k) = voxel_key(*p, inv_ds) else {
                want_rejected += 1;
                continue;
            };
            match sums.entry(k) {
                std::collections::hash_map::Entry::Vacant(v) => {
                    order.push(k);
                    v.insert((*p, 1));
                }
                std::collections::hash_map::Entry::Occupied(mut o) => {
                    let e = o.get_mut();
                    e.0 = [e.0[0] + p[0], e.0[1] + p[1], e.0[2] + p[2]];
                    e.1 += 1;
                }
            }
        }
        assert_eq!(rejected, want_rejected);
        let want: Vec<[f64; 3]> = order
            .iter()
            .map(|k| {
                let (s, n) = sums[k];
                s.map(|v| v / f64::from(n))
            })
            .collect();
        // Bits, so that −0 and 0 differ.
        let bits = |v: &[[f64; 3]]| v.iter().map(|p| p.map(f64::to_bits)).collect::<Vec<_>>();
        let want = bits(&want);
        let mut got = Vec::new();
        table.centroids_into(&mut got);
        assert_eq!(bits(&got), want, "round {round}");
        // Without range tests, for the points inside the range: the same table.
        let inside: Vec<[f64; 3]> = pts.iter().copied().filter(|&p| voxel_key(p, inv_ds).is_some()).collect();
        let mut unchecked = VoxelCentroids::<Slot>::default();
        assert_eq!(unchecked.add_all::<false>(&inside, inv_ds), 0);
        let mut got_unchecked = Vec::new();
        unchecked.centroids_into(&mut got_unchecked);
        assert_eq!(bits(&got_unchecked), want, "round {round}, unchecked");
        // Compact slots, for the points within half their span of 0 (most): the same
        // centroids as full keys give those points. Voxels a span apart share a compact key
        // (so the test can fail), which is why the shell path checks a scan's extent.
        let near: Vec<[f64; 3]> =
            inside.iter().copied().filter(|p| p.iter().all(|v| (v * inv_ds).abs() < 4000.0)).collect();
        assert!(near.len() > n / 2, "round {round}: most points are near");
        let mut wide = VoxelCentroids::<Slot>::default();
        wide.add_all::<false>(&near, inv_ds);
        compact.clear();
        compact.add_all::<false>(&near, inv_ds);
        let (mut want_near, mut got_compact) = (Vec::new(), Vec::new());
        wide.centroids_into(&mut want_near);
        compact.centroids_into(&mut got_compact);
        assert_eq!(bits(&got_compact), bits(&want_near), "round {round}, compact slots");
    }
}
