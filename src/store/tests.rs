use super::*;
use crate::core::{BlockKey, Integrator};
use crate::core::{block::BlockEvidence, posterior::Evidence};
use rusqlite::{Connection, params};

fn small_map() -> EvidenceMap {
    let params = MapParams { max_range_m: 5.0, ..Default::default() };
    let mut map = EvidenceMap::new(params);
    let pts: Vec<[f32; 3]> =
        (0..200).map(|i| [2.0 + (i % 20) as f32 * 0.05, -1.0 + (i / 20) as f32 * 0.1, 0.5]).collect();
    Integrator::new(params).integrate(&mut map, &pts, [0.0, 0.0, 0.3], 1);
    map
}

pub(super) fn cells(map: &EvidenceMap) -> Vec<(BlockKey, Vec<(i64, i64)>)> {
    map.block_keys_sorted()
        .into_iter()
        .map(|k| {
            let b = map.block(k).unwrap();
            (k, b.cells().map(|e| (e.a, e.b)).collect())
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
fn the_schema_in_the_file_is_the_documented_one() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    save_map(&path, &small_map()).unwrap();
    let c = Connection::open(&path).unwrap();
    let mut stmt = c.prepare("SELECT sql FROM sqlite_master WHERE type = 'table' ORDER BY rowid").unwrap();
    let sqls: Vec<String> = stmt.query_map([], |r| r.get(0)).unwrap().map(Result::unwrap).collect();
    assert_eq!(sqls, SCHEMA);
    let app: i64 = c.query_row("PRAGMA application_id", [], |r| r.get(0)).unwrap();
    assert_eq!(app.to_be_bytes()[4..], *b"BGKM");
}

#[test]
fn codec_round_trip_extremes_and_rejects_garbage() {
    let mut b = BlockEvidence::zeroed_wide();
    b.set(0, Evidence { a: i64::MAX, b: i64::MIN });
    b.set(511, Evidence { a: -1, b: 0 });
    let mut buf = Vec::new();
    encode_block(&b, &mut buf);
    assert_eq!(*decode_block(&buf).unwrap(), *b);
    assert!(decode_block(&buf).unwrap().is_wide(), "a block with hit mass loads wide");
    // A block without hit mass loads narrow, with the bytes of the same cells written wide.
    let mut free = BlockEvidence::zeroed_wide();
    free.set(7, Evidence { a: 0, b: -3 });
    let mut narrow = BlockEvidence::zeroed();
    narrow.set(7, Evidence { a: 0, b: -3 });
    let (mut wide_bytes, mut narrow_bytes) = (Vec::new(), Vec::new());
    encode_block(&free, &mut wide_bytes);
    encode_block(&narrow, &mut narrow_bytes);
    assert_eq!(wide_bytes, narrow_bytes, "the encoding does not depend on the layout");
    assert_eq!((wide_bytes[0], buf[0]), (2, 1), "encoding 2 without hit mass, 1 with");
    assert_eq!(wide_bytes.len(), 1 + 64 + 1, "encoding 2 keeps B alone");
    // The same cell in encoding 1 (as version 2 files hold it) reads the same.
    let mut both = wide_bytes.clone();
    both[0] = 1;
    both.insert(65, 0);
    assert!(*decode_block(&both).unwrap() == *free);
    assert!(decode_block(&wide_bytes[..65]).unwrap_err().contains("truncated"));
    let loaded = decode_block(&wide_bytes).unwrap();
    assert!(!loaded.is_wide() && *loaded == *free);
    assert!(decode_block(&buf[..buf.len() - 1]).unwrap_err().contains("truncated"));
    let mut extra = buf.clone();
    extra.push(0);
    assert!(decode_block(&extra).unwrap_err().contains("trailing"));
    assert!(decode_block(&[3]).unwrap_err().contains("encoding"));
    assert!(decode_block(&[]).is_err());
}

#[test]
fn other_versions_and_non_map_files_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    save_map(&path, &small_map()).unwrap();
    Connection::open(&path).unwrap().execute_batch("PRAGMA user_version = 99").unwrap();
    let err = load_map(&path).unwrap_err().to_string();
    assert!(err.contains("format version 99") && err.contains("m.bgkmap") && err.contains("newer"), "{err}");
    assert!(MapFile::open(&path).is_err(), "writers refuse it too");
    // Version 2 (the oldest this build reads): read as it is; upgraded when opened for writing.
    let v2 = "PRAGMA user_version = 2; UPDATE meta SET value = '2' WHERE key = 'format_version'";
    Connection::open(&path).unwrap().execute_batch(v2).unwrap();
    let versions = || -> (i64, String) {
        Connection::open(&path)
            .unwrap()
            .query_row(
                "SELECT user_version, (SELECT value FROM meta WHERE key = 'format_version') FROM pragma_user_version",
                [],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .unwrap()
    };
    assert!(load_map(&path).unwrap().same_blocks_as(&small_map()));
    assert_eq!(versions(), (2, "2".to_string()), "reading leaves it at version 2");
    MapFile::open(&path).unwrap();
    assert_eq!(versions(), (3, "3".to_string()), "a writer upgrades it first");
    Connection::open(&path).unwrap().execute_batch("PRAGMA user_version = 1").unwrap();
    let err = load_map(&path).unwrap_err().to_string();
    assert!(err.contains("format version 1 is not supported") && !err.contains("newer"), "{err}");

    let junk = dir.path().join("junk.bgkmap");
    std::fs::write(&junk, b"this is not sqlite at all, not even close............................").unwrap();
    assert!(matches!(load_map(&junk), Err(StoreError::NotAMap { .. })));
    assert!(matches!(load_map(&dir.path().join("missing")), Err(StoreError::Io { .. })));
}

/// Flips one byte of a block's data in the file itself (not through SQL): SQLite reads the page
/// fine, the block's checksum catches it.
pub(super) fn flip_block_byte(path: &std::path::Path) -> BlockKey {
    let c = Connection::open(path).unwrap();
    let (x, y, z, data): (i32, i32, i32, Vec<u8>) = c
        .query_row(
            "SELECT bx, by, bz, data FROM blocks WHERE length(data) < 2000 ORDER BY bx, by, bz LIMIT 1",
            [],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
        )
        .unwrap();
    c.execute_batch("PRAGMA wal_checkpoint(TRUNCATE)").unwrap();
    drop(c);
    let mut bytes = std::fs::read(path).unwrap();
    let at = bytes.windows(data.len()).position(|w| w == data.as_slice()).expect("block bytes in the file");
    bytes[at + data.len() / 2] ^= 0x10;
    std::fs::write(path, bytes).unwrap();
    BlockKey::new(x, y, z)
}

#[test]
fn corrupt_block_is_reported_with_its_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.bgkmap");
    save_map(&path, &small_map()).unwrap();
    let key = flip_block_byte(&path);
    let err = load_map(&path).unwrap_err();
    assert!(
        matches!(err, StoreError::CorruptBlock { x, y, z, .. } if BlockKey::new(x, y, z) == key),
        "{err}"
    );
    assert!(err.to_string().contains("checksum"), "{err}");
    let report = check::check_map(&path).unwrap();
    assert!(!report.is_ok());
    assert_eq!(report.corrupt_blocks.len(), 1);
    assert_eq!(report.corrupt_blocks[0].key, key);
    // A writer opens it anyway and keeps the other blocks.
    let opened = MapFile::open(&path).unwrap();
    assert_eq!(opened.corrupt.len(), 1);
    assert_eq!(opened.map.block_count() + 1, small_map().block_count());
    // Damage through SQL is found as well.
    let c = Connection::open(&path).unwrap();
    c.execute(
        "UPDATE blocks SET data = X'01' WHERE bx = ?1 AND by = ?2 AND bz = ?3",
        params![key.x, key.y, key.z],
    )
    .unwrap();
    assert!(matches!(load_map(&path), Err(StoreError::CorruptBlock { .. })));
}
