use super::*;
use crate::core::integrate::cell_points::SUB_FRAC;

/// Every slot once, for cubes, flat and elongated grids and a single slot; and neighbours
/// close: in a 16³ grid, each slot's neighbour along z comes within 8·8·8 slots of it in
/// the order where slot order puts it 256 apart for every slot.
#[test]
fn morton_order_visits_every_slot_once() {
    let mut order = Vec::new();
    for dims in [[1, 1, 1], [16, 16, 16], [38, 38, 10], [5, 1, 300], [1, 7, 2], [64, 3, 3]] {
        morton_order(dims, &mut order);
        let mut seen = order.clone();
        seen.sort_unstable();
        let n = (dims[0] * dims[1] * dims[2]) as u32;
        assert_eq!(seen, (0..n).collect::<Vec<_>>(), "dims {dims:?}");
    }
    morton_order([16, 16, 16], &mut order);
    let mut place = vec![0usize; order.len()];
    for (i, &s) in order.iter().enumerate() {
        place[s as usize] = i;
    }
    let near = (0..16 * 16 * 15).filter(|&s| place[s].abs_diff(place[s + 256]) < 512).count();
    assert!(near >= 16 * 16 * 15 * 7 / 8, "{near} of the z neighbours within 512 slots");
}

/// The bucket sort is the stable counting sort, with an even and an odd number of points
/// (the two halves it sorts side by side then differ in length).
#[test]
fn bucket_sort_is_stable() {
    for n in [0usize, 1, 2, 7, 1000, 1001] {
        // Cells spread over a 5 × 3 × 2 grid of buckets of 4 cells, in a scrambled order,
        // each point told apart by its sub-cell offset along x (no two alike below 1920).
        let pts: Vec<SubPoint> = (0..n)
            .map(|i| {
                let mut c = [(i * 7) % 20, (i * 13) % 12, (i * 5) % 8].map(|v| (v as i32) << SUB_FRAC);
                c[0] |= (i % (1 << SUB_FRAC)) as i32;
                (c, i % 3 == 0)
            })
            .collect();
        let mut scatter = Scatter::default();
        scatter.bucket(&pts, [0, 0, 0], [4, 2, 1], 2);
        let slot = |p: &SubPoint| scatter.grid.index(p.cell().map(|v| v >> 2));
        let mut want = pts.clone();
        want.sort_by_key(slot);
        assert_eq!(scatter.subs_sorted, want, "{n} points");
        for s in 0..scatter.grid.slots.len() {
            let (a, b) = (scatter.starts[s] as usize, scatter.starts[s + 1] as usize);
            assert!(want[a..b].iter().all(|p| slot(p) == s), "bucket {s} of {n} points");
        }
    }
}
