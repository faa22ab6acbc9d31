//! Golden messages: the PointCloud2 of docs/formats.md §5.3 byte for byte, and variants of it.

use super::*;

fn hex(s: &str) -> Vec<u8> {
    s.split_whitespace().map(|b| u8::from_str_radix(b, 16).unwrap()).collect()
}

fn le_f32(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// docs/formats.md §5.3: stamp 1 s 2 ns, frame "map", 1 × 2 points, fields x, y, z FLOAT32.
fn golden_cloud(points: [[f32; 3]; 2]) -> Vec<u8> {
    let mut m = hex("00 01 00 00  01 00 00 00 02 00 00 00  04 00 00 00 6d 61 70 00  01 00 00 00 02 00 00 00
         03 00 00 00
         02 00 00 00 78 00 00 00  00 00 00 00 07 00 00 00 01 00 00 00
         02 00 00 00 79 00 00 00  04 00 00 00 07 00 00 00 01 00 00 00
         02 00 00 00 7a 00 00 00  08 00 00 00 07 00 00 00 01 00 00 00
         00 00 00 00  0c 00 00 00 18 00 00 00  18 00 00 00");
    m.extend(le_f32(points.as_flattened()));
    m.push(1);
    m
}

#[test]
fn the_golden_point_cloud_decodes() {
    let bytes = golden_cloud([[1.0, 2.0, 3.0], [-4.5, 5.25, f32::NAN]]);
    assert_eq!(bytes.len(), 133);
    let c = PointCloud2::decode(&bytes).unwrap();
    assert_eq!(c.header, Header { stamp_ns: 1_000_000_002, frame_id: "map" });
    assert_eq!((c.height, c.width, c.point_step, c.row_step, c.is_dense), (1, 2, 12, 24, true));
    let names: Vec<_> = c.fields.iter().map(|f| (f.name, f.offset, f.datatype, f.count)).collect();
    assert_eq!(names, [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]);
    let p = c.points_xyz().unwrap();
    assert_eq!(p[0], [1.0, 2.0, 3.0]);
    assert_eq!(&p[1][..2], &[-4.5, 5.25]);
    assert!(p[1][2].is_nan(), "non-finite points are kept for the service to count");
}

#[test]
fn every_truncation_is_an_error_naming_a_field() {
    let bytes = golden_cloud([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    for len in 0..bytes.len() {
        match PointCloud2::decode(&bytes[..len]) {
            Err(Ros2Error::Truncated { field, .. }) => assert!(!field.is_empty()),
            other => panic!("prefix of {len} bytes: {other:?}"),
        }
    }
}

/// A cloud with padded records (`point_step`), rows padded to `row_step`, given fields.
fn cloud(fields: &[(&str, u32, u8)], step: u32, rows: u32, cols: u32, row_step: u32, data: &[u8]) -> Vec<u8> {
    let mut m = hex("00 01 00 00  05 00 00 00 00 00 00 00  06 00 00 00 6c 69 64 61 72 00 00 00");
    let u32le = |m: &mut Vec<u8>, v: u32| m.extend_from_slice(&v.to_le_bytes());
    let pad4 = |m: &mut Vec<u8>| m.resize((m.len() - 4).next_multiple_of(4) + 4, 0);
    u32le(&mut m, rows);
    u32le(&mut m, cols);
    u32le(&mut m, fields.len() as u32);
    for (name, offset, datatype) in fields {
        u32le(&mut m, name.len() as u32 + 1);
        m.extend_from_slice(name.as_bytes());
        m.push(0);
        pad4(&mut m);
        u32le(&mut m, *offset);
        m.push(*datatype);
        pad4(&mut m);
        u32le(&mut m, 1);
    }
    m.push(0);
    pad4(&mut m);
    u32le(&mut m, step);
    u32le(&mut m, row_step);
    u32le(&mut m, data.len() as u32);
    m.extend_from_slice(data);
    m.push(0);
    m
}

#[test]
fn padded_records_rows_and_float64_coordinates() {
    // 2 rows × 2 points, 32-byte records: intensity f32 at 0, x/y/z f64 at 8/16/24; rows padded
    // to 72 bytes.
    let fields = [("intensity", 0, 7), ("x", 8, 8), ("y", 16, 8), ("z", 24, 8)];
    let mut data = Vec::new();
    for row in 0..2 {
        for col in 0..2 {
            let v = f64::from(row * 10 + col);
            data.extend_from_slice(&[0xAA; 8]);
            for d in [v, v + 0.5, -v] {
                data.extend_from_slice(&d.to_le_bytes());
            }
        }
        data.extend_from_slice(&[0xEE; 8]);
    }
    let bytes = cloud(&fields, 32, 2, 2, 72, &data);
    let c = PointCloud2::decode(&bytes).unwrap();
    assert_eq!(c.header.frame_id, "lidar");
    let p = c.points_xyz().unwrap();
    assert_eq!(p, vec![[0.0, 0.5, -0.0], [1.0, 1.5, -1.0], [10.0, 10.5, -10.0], [11.0, 11.5, -11.0]]);
}

#[test]
fn wrong_point_fields_are_refused_with_the_reason() {
    let xyz = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)];
    let data = le_f32(&[1.0, 2.0, 3.0]);
    let err = |fields: &[(&str, u32, u8)], step, data: &[u8]| {
        PointCloud2::decode(&cloud(fields, step, 1, 1, step, data))
            .unwrap()
            .points_xyz()
            .unwrap_err()
            .to_string()
    };
    assert!(err(&xyz[..2], 12, &data).contains("no field named \"z\""));
    assert!(err(&[("x", 0, 7), ("y", 4, 7), ("z", 8, 3)], 12, &data).contains("datatype 3"));
    assert!(err(&xyz, 10, &data).contains("exceeds point_step 10"));
    assert!(err(&xyz, 12, &data[..8]).contains("PointCloud2.data"));
    let mut big = cloud(&xyz, 12, 1, 1, 12, &data);
    let flag = big.len() - 1 - 12 - 4 - 4 - 4 - 4; // is_bigendian, before 3 pad bytes
    big[flag] = 1;
    let e = PointCloud2::decode(&big).unwrap().points_xyz().unwrap_err();
    assert!(e.to_string().contains("is_bigendian"), "{e}");
}

#[test]
fn pose_stamped_aligns_its_doubles_after_the_frame() {
    // frame "odom" (length 5): the f64s start at body offset 24 (docs/formats.md §5.4).
    let mut m = hex("00 01 00 00  07 00 00 00 00 00 00 00  05 00 00 00 6f 64 6f 6d 00  00 00 00 00 00 00 00");
    for v in [1.0f64, 2.0, 3.0, 0.0, 0.0, 0.6, 0.8] {
        m.extend_from_slice(&v.to_le_bytes());
    }
    assert_eq!(m.len(), 4 + 24 + 56);
    let p = PoseStamped::decode(&m).unwrap();
    assert_eq!(p.header, Header { stamp_ns: 7_000_000_000, frame_id: "odom" });
    assert_eq!(p.pose, Pose { translation_m: [1.0, 2.0, 3.0], rotation_wxyz: [0.8, 0.0, 0.0, 0.6] });
}

#[test]
fn tf_messages_carry_parent_child_and_transform() {
    // One transform odom → base_link; translation at body offset 40, 96 body bytes (§5.4).
    let mut m = hex("00 01 00 00  01 00 00 00  03 00 00 00 04 00 00 00  05 00 00 00 6f 64 6f 6d 00
         00 00 00  0a 00 00 00 62 61 73 65 5f 6c 69 6e 6b 00  00 00");
    assert_eq!(m.len() - 4, 40);
    for v in [0.5f64, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0] {
        m.extend_from_slice(&v.to_le_bytes());
    }
    assert_eq!(m.len() - 4, 96);
    let tf = decode_tf_message(&m).unwrap();
    assert_eq!(tf.len(), 1);
    assert_eq!((tf[0].header.frame_id, tf[0].child_frame_id), ("odom", "base_link"));
    assert_eq!(tf[0].header.stamp_ns, 3_000_000_004);
    assert_eq!(tf[0].parent_from_child, Pose::at([0.5, 0.0, 0.0]));
}
