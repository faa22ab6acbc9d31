#![allow(clippy::unwrap_used)]
//! Configured limits are answers, not crashes: an oversized gRPC message is RESOURCE_EXHAUSTED,
//! an oversized HTTP body 413, a box over the limit INVALID_ARGUMENT / 400 — and none of them
//! changes the map.
#![cfg(feature = "server")]

use crate::common;

use bgkmap::api::pb;
use bgkmap::api::pb::map_service_client::MapServiceClient;
use std::io::{Read, Write};

/// A minimal HTTP/1.1 POST; returns the status code and body.
fn http_post(addr: std::net::SocketAddr, path: &str, body: &[u8]) -> (u16, String) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).unwrap();
    let _ = s.write_all(body); // the server may answer 413 and close before reading it all
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    let text = String::from_utf8_lossy(&out).to_string();
    let code = text.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    (code, text)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_messages_and_boxes_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("bgkmap.toml");
    std::fs::write(&config, "max_message_bytes = 1000000\nmax_box_cells = 1000\n").unwrap();
    let data = dir.path().join("data");
    let server = common::start_serve(&data, &["--config", config.to_str().unwrap()]);
    let mut client =
        MapServiceClient::connect(server.grpc_url()).await.unwrap().max_encoding_message_size(64 << 20);
    client
        .create_map(pb::CreateMapRequest { map: "m".into(), params: Some(pb::MapParams::default()) })
        .await
        .unwrap();

    // 200k points = 2.4 MB of xyz: over the 1 MB limit.
    let xyz: Vec<u8> =
        (0..200_000).flat_map(|i| [1.0f32 + i as f32 * 1e-5, 0.0, 0.5]).flat_map(f32::to_le_bytes).collect();
    let scan = pb::Scan {
        source: "big".into(),
        seq: 1,
        world_from_sensor: Some(pb::Pose { translation: vec![0.0; 3], rotation: vec![1.0, 0.0, 0.0, 0.0] }),
        frame: pb::Frame::World as i32,
        xyz_f32: xyz,
        max_range: None,
        stamp_nanos: None,
    };
    let err = client
        .insert_scan(pb::InsertScanRequest { map: "m".into(), scan: Some(scan), wait_applied: false })
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::ResourceExhausted, "{err:?}");
    assert!(err.message().contains("limit of 1000000 bytes"), "{}", err.message());

    let body = format!("{{\"points\": [{}]}}", vec!["[1.0, 2.0, 0.5]"; 100_000].join(","));
    let (code, text) = http_post(server.http_addr, "/v1/maps/m/query/points", body.as_bytes());
    assert_eq!(code, 413, "{text}");

    let b =
        pb::QueryBoxRequest { map: "m".into(), min: vec![0.0; 3], max: vec![10.0; 3], ..Default::default() };
    let err = client.query_box(b).await.unwrap_err();
    assert_eq!(err.code(), tonic::Code::InvalidArgument);
    assert!(err.message().contains("limit of 1000"), "{}", err.message());
    let (code, text) =
        http_post(server.http_addr, "/v1/maps/m/query/box", br#"{"min":[0,0,0],"max":[10,10,10]}"#);
    assert_eq!(code, 400, "{text}");
    assert!(text.contains("limit of 1000"), "{text}");

    let info = client.get_map(pb::GetMapRequest { map: "m".into() }).await.unwrap().into_inner();
    assert_eq!(info.version, 0, "nothing was applied");
    assert_eq!(server.terminate().code(), Some(0));
}
