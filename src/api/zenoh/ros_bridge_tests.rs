//! The bridge fed with hand-encoded CDR messages (the decoders' golden tests are in
//! `io::ros2`; Python `rosbags` encodes the integration tests' messages independently).

use super::*;

const S: i64 = 1_000_000_000;

/// A minimal CDR writer: little-endian, aligned from the body start.
struct Cdr(Vec<u8>);

impl Cdr {
    fn new() -> Self {
        Self(vec![0, 1, 0, 0])
    }
    fn align(&mut self, n: usize) {
        let body = self.0.len() - 4;
        self.0.resize(4 + body.next_multiple_of(n), 0);
    }
    fn u32(&mut self, v: u32) -> &mut Self {
        self.align(4);
        self.0.extend_from_slice(&v.to_le_bytes());
        self
    }
    fn f64(&mut self, v: f64) -> &mut Self {
        self.align(8);
        self.0.extend_from_slice(&v.to_le_bytes());
        self
    }
    fn string(&mut self, s: &str) -> &mut Self {
        self.u32(s.len() as u32 + 1);
        self.0.extend_from_slice(s.as_bytes());
        self.0.push(0);
        self
    }
    fn header(&mut self, stamp_ns: i64, frame: &str) -> &mut Self {
        self.u32((stamp_ns / S) as u32).u32((stamp_ns % S) as u32).string(frame)
    }
    fn pose(&mut self, p: &Pose) -> &mut Self {
        let [w, x, y, z] = p.rotation_wxyz;
        for v in p.translation_m.into_iter().chain([x, y, z, w]) {
            self.f64(v);
        }
        self
    }
}

fn cloud(stamp_ns: i64, frame: &str, points: &[[f32; 3]], names: [&str; 3]) -> Vec<u8> {
    let mut c = Cdr::new();
    c.header(stamp_ns, frame).u32(1).u32(points.len() as u32).u32(3);
    for (i, name) in names.iter().enumerate() {
        c.string(name).u32(4 * i as u32);
        c.0.push(7);
        c.u32(1);
    }
    c.0.push(0);
    c.u32(12).u32(12 * points.len() as u32).u32(12 * points.len() as u32);
    c.0.extend(points.iter().flatten().flat_map(|v| v.to_le_bytes()));
    c.0.push(1);
    c.0
}

fn xyz_cloud(stamp_ns: i64, frame: &str, points: &[[f32; 3]]) -> Incoming {
    Incoming::Cloud(cloud(stamp_ns, frame, points, ["x", "y", "z"]))
}

fn pose_msg(stamp_ns: i64, frame: &str, p: &Pose) -> Incoming {
    let mut c = Cdr::new();
    c.header(stamp_ns, frame).pose(p);
    Incoming::Pose(c.0)
}

fn tf_msg(edges: &[(i64, &str, &str, Pose)], is_static: bool) -> Incoming {
    let mut c = Cdr::new();
    c.u32(edges.len() as u32);
    for (stamp, parent, child, p) in edges {
        c.header(*stamp, parent).string(child).pose(p);
    }
    Incoming::Tf { payload: c.0, is_static }
}

fn config(pose: RosPose) -> RosTopicConfig {
    RosTopicConfig {
        map: "m".into(),
        cloud_topic: "/r1/points".into(),
        source: None,
        domain_id: 0,
        cloud_key: None,
        pose,
        pose_topic: Some("/r1/pose".into()),
        pose_key: None,
        world_frame: "map".into(),
        sensor_frame: None,
    }
}

fn scan(out: &[Outcome]) -> &ScanInput {
    match out {
        [Outcome::Scan(s)] => s,
        other => panic!("expected one scan, got {other:?}"),
    }
}

fn kind(out: &[Outcome]) -> &'static str {
    match out {
        [Outcome::Reject { kind, .. } | Outcome::Fault { kind, .. }] => kind,
        other => panic!("expected one refusal, got {other:?}"),
    }
}

const PTS: [[f32; 3]; 2] = [[1.0, 2.0, 0.5], [f32::NAN, 0.0, 0.0]];

#[test]
fn identity_clouds_become_scans_identified_by_their_stamp() {
    let mut b = RosBridge::new(&config(RosPose::Identity));
    let out = b.handle(xyz_cloud(5 * S + 7, "map", &PTS));
    let s = scan(&out);
    assert_eq!((s.source.as_str(), s.seq, s.frame), ("/r1/points", 5 * S as u64 + 7, PointFrame::World));
    assert_eq!(s.world_from_sensor, Pose::IDENTITY);
    assert_eq!(s.points.len(), 2, "non-finite points reach the service, which counts them");
}

#[test]
fn clouds_wait_for_the_pose_at_their_stamp() {
    let mut b = RosBridge::new(&config(RosPose::Topic));
    let p1 = Pose { translation_m: [1.0, 2.0, 0.5], rotation_wxyz: [0.8, 0.0, 0.0, 0.6] };
    assert!(b.handle(pose_msg(S, "map", &Pose::IDENTITY)).is_empty());
    assert!(b.handle(xyz_cloud(3 * S, "lidar", &PTS)).is_empty(), "no pose at 3 s yet");
    let out = b.handle(pose_msg(3 * S, "/map", &p1)); // ROS 1 style frame names are fine
    let s = scan(&out);
    assert_eq!((s.seq, s.frame, s.world_from_sensor), (3 * S as u64, PointFrame::Sensor, p1));
    // Between two poses: interpolated (halfway in translation).
    let s = scan(&b.handle(xyz_cloud(2 * S, "map", &PTS))).clone();
    assert_eq!((s.frame, s.world_from_sensor.translation_m), (PointFrame::World, [0.5, 1.0, 0.25]));
    assert_eq!(kind(&b.handle(xyz_cloud(S / 2, "map", &PTS))), "no pose", "older than every pose");
}

#[test]
fn the_tf_chain_poses_sensor_frame_clouds() {
    let mut b = RosBridge::new(&config(RosPose::Tf));
    let odom = Pose::at([10.0, 0.0, 0.0]);
    let base = Pose::at([1.0, 1.0, 0.0]);
    assert!(b.handle(xyz_cloud(2 * S, "lidar", &PTS)).is_empty());
    assert!(b.handle(tf_msg(&[(0, "map", "odom", odom)], true)).is_empty(), "no odom → lidar yet");
    let out = b.handle(tf_msg(&[(2 * S, "odom", "lidar", base)], false));
    let s = scan(&out);
    assert_eq!((s.frame, s.world_from_sensor), (PointFrame::Sensor, Pose::at([11.0, 1.0, 0.0])));
}

#[test]
fn bad_clouds_are_refused_with_their_kind_and_bad_poses_are_faults() {
    let mut b = RosBridge::new(&config(RosPose::Topic));
    assert_eq!(kind(&b.handle(Incoming::Cloud(vec![0, 1, 0, 0, 1]))), "cdr");
    assert_eq!(kind(&b.handle(Incoming::Cloud(cloud(S, "map", &PTS, ["x", "y", "w"])))), "point fields");
    assert_eq!(kind(&b.handle(xyz_cloud(0, "map", &PTS))), "stamp");
    assert_eq!(kind(&b.handle(pose_msg(S, "odom", &Pose::IDENTITY))), "pose");
    assert_eq!(kind(&b.handle(Incoming::Pose(vec![0, 1, 0, 0]))), "pose");
    assert_eq!(kind(&b.handle(tf_msg(&[(S, "map", "map", Pose::IDENTITY)], false))), "tf");
}

#[test]
fn waiting_is_bounded_and_shutdown_refuses_the_rest() {
    let mut b = RosBridge::new(&config(RosPose::Topic));
    for i in 1..=MAX_PENDING as i64 {
        assert!(b.handle(xyz_cloud(i * S, "map", &PTS)).is_empty());
    }
    assert_eq!(kind(&b.handle(xyz_cloud(100 * S, "map", &PTS))), "no pose");
    let rest = b.finish();
    assert_eq!(rest.len(), MAX_PENDING);
    assert!(rest.iter().all(|o| matches!(o, Outcome::Reject { kind: "no pose", .. })));
}
