use super::*;

const S: i64 = 1_000_000_000;

fn yaw(theta: f64) -> [f64; 4] {
    [(theta / 2.0).cos(), 0.0, 0.0, (theta / 2.0).sin()]
}

fn close(a: &Pose, b: &Pose) -> bool {
    let d = |x: &[f64], y: &[f64]| x.iter().zip(y).all(|(u, v)| (u - v).abs() < 1e-12);
    d(&a.translation_m, &b.translation_m) && d(&a.rotation_wxyz, &b.rotation_wxyz)
}

#[test]
fn history_answers_exact_interpolated_wait_and_never() {
    let mut h = PoseHistory::default();
    assert_eq!(h.at(0), Lookup::Wait);
    let p0 = Pose { translation_m: [0.0, 0.0, 1.0], rotation_wxyz: yaw(0.0) };
    let p1 = Pose { translation_m: [2.0, 4.0, 1.0], rotation_wxyz: yaw(1.0) };
    h.insert(10 * S, p1).unwrap();
    h.insert(9 * S, p0).unwrap(); // out of order is fine
    assert_eq!(h.at(10 * S), Lookup::Ready(p1));
    assert_eq!(h.at(9 * S), Lookup::Ready(p0));
    let Lookup::Ready(mid) = h.at(9 * S + S / 4) else { panic!() };
    assert!(close(&mid, &Pose { translation_m: [0.5, 1.0, 1.0], rotation_wxyz: yaw(0.25) }), "{mid:?}");
    assert_eq!(h.at(10 * S + 1), Lookup::Wait);
    assert!(matches!(h.at(9 * S - 1), Lookup::Never(_)));
    assert!(h.insert(11 * S, Pose { rotation_wxyz: [2.0, 0.0, 0.0, 0.0], ..p0 }).is_err());
}

#[test]
fn history_forgets_samples_older_than_ten_seconds() {
    let mut h = PoseHistory::default();
    for i in 0..=20 {
        h.insert(i * S, Pose::at([i as f64, 0.0, 0.0])).unwrap();
    }
    assert!(matches!(h.at(9 * S), Lookup::Never(_)));
    assert_eq!(h.at(10 * S), Lookup::Ready(Pose::at([10.0, 0.0, 0.0])));
}

#[test]
fn the_tree_composes_static_and_moving_edges_up_to_the_world() {
    let mut tf = TfTree::default();
    let odom = Pose { translation_m: [1.0, 0.0, 0.0], rotation_wxyz: yaw(std::f64::consts::FRAC_PI_2) };
    tf.insert("map", "odom", 0, odom, true).unwrap();
    assert_eq!(tf.lookup("map", "lidar", 5 * S), Lookup::Wait);
    tf.insert("odom", "base_link", 4 * S, Pose::at([0.0, 0.0, 0.0]), false).unwrap();
    tf.insert("odom", "base_link", 6 * S, Pose::at([2.0, 0.0, 0.0]), false).unwrap();
    tf.insert("base_link", "lidar", 0, Pose::at([0.0, 0.0, 0.5]), true).unwrap();
    // map ← odom (1, 0, 0) yawed 90°; odom ← base_link (1, 0, 0) at 5 s; base_link ← lidar z 0.5.
    let Lookup::Ready(p) = tf.lookup("map", "lidar", 5 * S) else { panic!() };
    let want = Pose { translation_m: [1.0, 1.0, 0.5], rotation_wxyz: yaw(std::f64::consts::FRAC_PI_2) };
    assert!(close(&p, &want), "{p:?}");
    assert_eq!(tf.lookup("map", "map", 0), Lookup::Ready(Pose::IDENTITY));
    assert_eq!(tf.lookup("map", "lidar", 7 * S), Lookup::Wait);
    assert!(matches!(tf.lookup("map", "lidar", 3 * S), Lookup::Never(_)));
}

#[test]
fn one_edge_is_returned_exactly_and_cycles_end() {
    let mut tf = TfTree::default();
    let p = Pose { translation_m: [0.1, 0.2, 0.3], rotation_wxyz: yaw(0.3) };
    tf.insert("map", "lidar", S, p, false).unwrap();
    assert_eq!(tf.lookup("map", "lidar", S), Lookup::Ready(p));
    tf.insert("b", "a", 0, Pose::IDENTITY, true).unwrap();
    tf.insert("a", "b", 0, Pose::IDENTITY, true).unwrap();
    assert!(matches!(tf.lookup("map", "a", 0), Lookup::Never(_)));
    assert!(tf.insert("x", "x", 0, Pose::IDENTITY, true).is_err());
}
