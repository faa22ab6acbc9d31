//! A map file opened for incremental writing (the server's view of a map file).

use super::{StoreError, create_schema, encode_block, open_with, read_map, sql};
use crate::core::evidence::BlockEvidence;
use crate::core::{BlockKey, EvidenceMap, MapParams};
use rusqlite::{Connection, OpenFlags, params};
use std::path::{Path, PathBuf};

/// The identity of a scan in a map: `(source, seq)`.
pub type ScanId = (String, u64);

/// A map file opened for writing, with what it holds.
#[derive(Debug)]
pub struct OpenedMap {
    pub file: MapFile,
    pub map: EvidenceMap,
    pub scans: Vec<ScanId>,
}

/// A writable map file: blocks are upserted and scan identities recorded in one transaction.
#[derive(Debug)]
pub struct MapFile {
    conn: Connection,
    path: PathBuf,
}

impl MapFile {
    /// Creates a new, empty map file; refuses to replace an existing file.
    pub fn create(path: &Path, map_params: &MapParams) -> Result<Self, StoreError> {
        if path.exists() {
            let error = std::io::Error::new(std::io::ErrorKind::AlreadyExists, "map file already exists");
            return Err(StoreError::Io { path: path.to_path_buf(), error });
        }
        let tmp = super::temp_sibling(path);
        let _ = std::fs::remove_file(&tmp);
        let result = (|| {
            let mut conn = Connection::open(&tmp).map_err(sql(&tmp))?;
            create_schema(&mut conn, &tmp, map_params)?;
            conn.close().map_err(|(_, err)| sql(&tmp)(err))?;
            std::fs::rename(&tmp, path).map_err(|error| StoreError::Io { path: path.to_path_buf(), error })
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        result?;
        Ok(Self::open(path)?.file)
    }

    /// Opens an existing map file for writing (WAL mode); returns it with its map and the
    /// identities of the scans it holds.
    pub fn open(path: &Path) -> Result<OpenedMap, StoreError> {
        let conn = open_with(path, OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_NO_MUTEX)?;
        let e = sql(path);
        conn.execute_batch("PRAGMA journal_mode = WAL; PRAGMA synchronous = NORMAL;").map_err(&e)?;
        let map = read_map(&conn, path)?;
        let mut stmt = conn.prepare("SELECT source, seq FROM scans").map_err(&e)?;
        let scans = stmt
            .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)? as u64)))
            .map_err(&e)?
            .collect::<Result<Vec<_>, _>>()
            .map_err(&e)?;
        drop(stmt);
        Ok(OpenedMap { file: Self { conn, path: path.to_path_buf() }, map, scans })
    }

    /// Wraps a connection to a file whose schema is already written (rollback journal mode).
    pub(super) fn from_conn(conn: Connection, path: &Path) -> Self {
        Self { conn, path: path.to_path_buf() }
    }

    /// Closes the file, reporting a failure to flush it.
    pub(super) fn close(self) -> Result<(), StoreError> {
        let path = self.path;
        self.conn.close().map_err(|(_, err)| sql(&path)(err))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes the given blocks (`None` or an empty block deletes the row) and records the scan
    /// identities, atomically.
    pub fn commit(
        &mut self,
        blocks: &[(BlockKey, Option<&BlockEvidence>)],
        scans: &[(&str, u64)],
    ) -> Result<(), StoreError> {
        let e = sql(&self.path);
        let tx = self.conn.transaction().map_err(&e)?;
        {
            let mut upsert = tx
                .prepare_cached(
                    "INSERT INTO blocks (bx, by, bz, data, crc32) VALUES (?1, ?2, ?3, ?4, ?5)
                     ON CONFLICT (bx, by, bz) DO UPDATE SET data = excluded.data, crc32 = excluded.crc32",
                )
                .map_err(&e)?;
            let mut delete =
                tx.prepare_cached("DELETE FROM blocks WHERE bx = ?1 AND by = ?2 AND bz = ?3").map_err(&e)?;
            let mut buf = Vec::new();
            for (key, block) in blocks {
                match block.filter(|b| !b.is_empty()) {
                    Some(b) => {
                        buf.clear();
                        encode_block(b, &mut buf);
                        upsert
                            .execute(params![key.x, key.y, key.z, &buf, crc32fast::hash(&buf)])
                            .map_err(&e)?;
                    }
                    None => {
                        delete.execute(params![key.x, key.y, key.z]).map_err(&e)?;
                    }
                }
            }
            let mut scan =
                tx.prepare_cached("INSERT INTO scans (source, seq) VALUES (?1, ?2)").map_err(&e)?;
            for (source, seq) in scans {
                scan.execute(params![source, *seq as i64]).map_err(&e)?;
            }
        }
        tx.commit().map_err(&e)
    }
}
