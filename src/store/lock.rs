//! The writer lock of a map file: an exclusive advisory lock (`flock`) on the sibling
//! `<file>-lock`, held by whoever changes the file in place (the server for as long as the map
//! is open; `bgkmap retract` / `repose` while they run). The lock dies with its process, so a
//! crash never leaves a map locked; the `-lock` file itself may stay and is harmless.

use super::StoreError;
use std::fs::{File, OpenOptions, TryLockError};
use std::path::{Path, PathBuf};

/// A held writer lock; released when dropped.
#[derive(Debug)]
pub struct MapLock {
    _file: File,
    path: PathBuf,
}

/// The lock file of a map file: `<file>-lock`.
pub fn lock_path(map_path: &Path) -> PathBuf {
    let mut name = map_path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push("-lock");
    map_path.with_file_name(name)
}

impl MapLock {
    /// Takes the writer lock of `map_path`, or fails at once with [`StoreError::Locked`].
    pub fn acquire(map_path: &Path) -> Result<Self, StoreError> {
        let path = lock_path(map_path);
        let io = |error| StoreError::Io { path: path.clone(), error };
        let file = OpenOptions::new().create(true).truncate(false).write(true).open(&path).map_err(io)?;
        match file.try_lock() {
            Ok(()) => Ok(Self { _file: file, path }),
            Err(TryLockError::WouldBlock) => {
                Err(StoreError::Locked { path: map_path.to_path_buf(), lock: path })
            }
            Err(TryLockError::Error(error)) => Err(io(error)),
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_writer_is_refused_until_the_first_lets_go() {
        let dir = tempfile::tempdir().unwrap();
        let map = dir.path().join("m.bgkmap");
        let first = MapLock::acquire(&map).unwrap();
        assert!(first.path().ends_with("m.bgkmap-lock"));
        let err = MapLock::acquire(&map).unwrap_err();
        assert!(matches!(err, StoreError::Locked { .. }), "{err}");
        assert!(err.to_string().contains("in use by another process"), "{err}");
        drop(first);
        MapLock::acquire(&map).unwrap();
    }
}
