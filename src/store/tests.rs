use super::*;
use crate::core::Integrator;
use crate::core::evidence::BlockEvidence;

fn small_map() -> EvidenceMap {
    let params = MapParams { max_range_m: 5.0, ..Default::default() };
    let mut map = EvidenceMap::new(params);
    let pts: Vec<[f32; 3]> =
        (0..200).map(|i| [2.0 + (i % 20) as f32 * 0.05, -1.0 + (i / 20) as f32 * 0.1, 0.5]).collect();
    Integrator::new(params).integrate(&mut map, &pts, [0.0, 0.0, 0.3], 1);
    map
}

fn cells(map: &EvidenceMap) -> Vec<(BlockKey, Vec<(i64, i64)>)> {
    map.block_keys_sorted()
        .into_iter()
        .map(|k| {
            let b = map.block(k).unwrap();
            (k, b.a.iter().copied().zip(b.b.iter().copied()).collect())
        })
        .collect()
}

#[test]
fn save_load_round_trip_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    let map = small_map();
    save_map(&path, &map).unwrap();
    let back = load_map(&path).unwrap();
    assert_eq!(back.params(), map.params());
    assert_eq!(cells(&back), cells(&map));
    assert!(back.block_count() > 0);
    // No temporary files left behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn codec_round_trip_extremes_and_rejects_garbage() {
    let mut b = BlockEvidence::zeroed();
    b.a[0] = i64::MAX;
    b.b[0] = i64::MIN;
    b.a[511] = -1;
    let mut buf = Vec::new();
    encode_block(&b, &mut buf);
    assert_eq!(*decode_block(&buf).unwrap(), *b);
    assert!(decode_block(&buf[..buf.len() - 1]).unwrap_err().contains("truncated"));
    let mut extra = buf.clone();
    extra.push(0);
    assert!(decode_block(&extra).unwrap_err().contains("trailing"));
    assert!(decode_block(&[2]).unwrap_err().contains("encoding"));
    assert!(decode_block(&[]).is_err());
}

#[test]
fn wrong_version_and_non_map_files_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    save_map(&path, &small_map()).unwrap();
    Connection::open(&path).unwrap().execute_batch("PRAGMA user_version = 99").unwrap();
    let err = load_map(&path).unwrap_err().to_string();
    assert!(err.contains("format version 99") && err.contains("m.bgkmap"), "{err}");

    let junk = dir.path().join("junk.bgkmap");
    std::fs::write(&junk, b"this is not sqlite at all, not even close............................").unwrap();
    assert!(matches!(load_map(&junk), Err(StoreError::NotAMap { .. })));
    assert!(matches!(load_map(&dir.path().join("missing")), Err(StoreError::Io { .. })));
}

#[test]
fn corrupt_block_is_reported_with_its_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    save_map(&path, &small_map()).unwrap();
    Connection::open(&path)
        .unwrap()
        .execute_batch(
            "UPDATE blocks SET data = zeroblob(70) WHERE rowid IN (SELECT rowid FROM blocks LIMIT 1)",
        )
        .unwrap_or_else(|_| {
            let c = Connection::open(&path).unwrap();
            let (x, y, z): (i32, i32, i32) = c
                .query_row("SELECT bx, by, bz FROM blocks LIMIT 1", [], |r| {
                    Ok((r.get(0)?, r.get(1)?, r.get(2)?))
                })
                .unwrap();
            c.execute(
                "UPDATE blocks SET data = X'01' WHERE bx = ?1 AND by = ?2 AND bz = ?3",
                params![x, y, z],
            )
            .unwrap();
        });
    let err = load_map(&path).unwrap_err();
    assert!(matches!(err, StoreError::CorruptBlock { .. }), "{err}");
    assert!(err.to_string().contains("checksum"), "{err}");
}
