use super::*;
use crate::core::{Integrator, MapParams};

/// The built-in room after 4 simulated scans (also used by the ray tests).
pub(crate) fn room_map() -> EvidenceMap {
    let params = MapParams::default();
    let mut map = EvidenceMap::new(params);
    let (_, scans) = crate::sim::simulate(0, 4, &crate::sim::Lidar::default());
    let mut integ = Integrator::new(params);
    for s in &scans {
        integ.integrate(&mut map, &s.points_world, s.origin, 1);
    }
    map
}

#[test]
fn batched_points_equal_one_point_at_a_time() {
    // 2,000 points (62 full rounds and a partial one) over and around the room: cells with
    // and without evidence, blocks that do not exist, points outside the key range.
    let map = room_map();
    let th = Thresholds::default();
    let mut pts: Vec<[f64; 3]> = (0..1997)
        .map(|i| {
            let t = i as f64;
            [(t * 0.0137) % 12.0 - 1.0, (t * 0.0291) % 9.0 - 1.0, (t * 0.0071) % 3.5 - 0.5]
        })
        .collect();
    pts.extend([[f64::NAN, 0.0, 0.0], [1e12, 0.0, 0.0], [0.0, -1e12, 0.0]]);
    let ans = query_points(&map, &pts, &th);
    assert_eq!(ans.len(), pts.len());
    let mut with_evidence = 0;
    for (p, a) in pts.iter().zip(&ans) {
        let expected =
            CellKey::from_point(*p, 0.1).map(|cell| PointAnswer { cell, estimate: map.estimate(cell, &th) });
        assert_eq!(*a, expected, "point {p:?}");
        with_evidence += usize::from(a.is_some_and(|a| !a.estimate.evidence.is_empty()));
    }
    assert!(with_evidence > 100 && with_evidence < 1900, "{with_evidence} points with evidence");
}

#[test]
fn point_box_and_ray_queries_agree_with_cell_estimates() {
    let map = room_map();
    let th = Thresholds::default();
    let pts = [[5.0, 2.0, 0.7], [0.05, 5.0, 1.0], [1000.0, 0.0, 0.0], [f64::NAN, 0.0, 0.0]];
    let ans = query_points(&map, &pts, &th);
    assert!(ans[3].is_none());
    for (p, a) in pts.iter().zip(&ans).take(3) {
        let a = a.unwrap();
        assert_eq!(a.cell, CellKey::from_point(*p, 0.1).unwrap());
        assert_eq!(a.estimate, map.estimate(a.cell, &th));
    }
    // The box answer equals the per-cell answers for cells with evidence.
    let q = BoxQuery { min_world: [4.0, 1.0, 0.0], max_world: [5.0, 2.0, 1.0], state: None, coarsen: 0 };
    let cells = query_box(&map, &q, &th, 1_000_000).unwrap();
    assert!(!cells.is_empty());
    for c in &cells {
        assert_eq!(c.estimate, map.estimate(c.min_cell, &th));
    }
    let n_with_evidence = (0..11)
        .flat_map(|z| (10..21).flat_map(move |y| (40..51).map(move |x| CellKey::new(x, y, z))))
        .filter(|c| !map.evidence(*c).is_empty())
        .count();
    assert_eq!(cells.len(), n_with_evidence);
    // Coarsening sums evidence: total mass is preserved.
    let coarse = query_box(&map, &BoxQuery { coarsen: 2, ..q }, &th, 1_000_000).unwrap();
    let sum = |v: &[BoxCell]| v.iter().map(|c| c.estimate.evidence.a).sum::<i64>();
    assert_eq!(sum(&coarse), sum(&cells));
    // Limits.
    assert!(matches!(query_box(&map, &q, &th, 10), Err(BoxError::TooLarge { .. })));
    let bad = BoxQuery { min_world: [1.0, 0.0, 0.0], max_world: [0.0, 1.0, 1.0], ..q };
    assert_eq!(query_box(&map, &bad, &th, 100), Err(BoxError::Malformed));
}
