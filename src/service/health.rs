//! Why a map is read-only, and when to try writing again.
//!
//! A failed write (disk full, read-only file system, I/O error) turns the map read-only: ingest
//! is refused with [`ServiceError::ReadOnly`](super::ServiceError::ReadOnly) while queries keep
//! answering from the last snapshot. Recovery needs no operator:
//! - a failed **journal** write: after the retry interval the next submitted scan is let
//!   through as a probe; if it is journaled, the map is writable again;
//! - a failed **integration** (blocks) write: the writer retries the same batch every retry
//!   interval (the scans are durable in the journal meanwhile); success makes it writable.
//!
//! Corrupt blocks or journal records make the map read-only until it is repaired and reopened.

use std::sync::Mutex;
use std::time::{Duration, Instant};

#[derive(Debug, Clone)]
struct Fault {
    reason: String,
    retry_at: Instant,
}

#[derive(Debug, Default)]
struct State {
    journal: Option<Fault>,
    apply: Option<Fault>,
    damaged: Option<String>,
}

/// The write health of one map.
#[derive(Debug)]
pub(crate) struct Faults {
    state: Mutex<State>,
    retry: Duration,
}

impl Faults {
    pub fn new(retry: Duration) -> Self {
        Self { state: Mutex::default(), retry }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Whether a scan may be submitted now: `Err(reason)` while read-only, except for one
    /// probe per retry interval after a journal failure.
    pub fn admit(&self) -> Result<(), String> {
        let mut s = self.lock();
        if let Some(d) = &s.damaged {
            return Err(d.clone());
        }
        if let Some(f) = &s.apply {
            return Err(f.reason.clone());
        }
        let now = Instant::now();
        match &mut s.journal {
            Some(f) if now < f.retry_at => Err(f.reason.clone()),
            Some(f) => {
                f.retry_at = now + self.retry;
                Ok(())
            }
            None => Ok(()),
        }
    }

    pub fn journal_failed(&self, reason: String) {
        self.lock().journal = Some(Fault {
            reason: format!("journal write failed: {reason}"),
            retry_at: Instant::now() + self.retry,
        });
    }

    pub fn journal_ok(&self) {
        self.lock().journal = None;
    }

    pub fn apply_failed(&self, reason: String) {
        let retry_at = Instant::now() + self.retry;
        self.lock().apply = Some(Fault { reason: format!("integration write failed: {reason}"), retry_at });
    }

    pub fn apply_ok(&self) {
        self.lock().apply = None;
    }

    /// True when an integration retry is not due yet.
    pub fn apply_backing_off(&self) -> bool {
        self.lock().apply.as_ref().is_some_and(|f| Instant::now() < f.retry_at)
    }

    pub fn set_damaged(&self, reason: String) {
        self.lock().damaged = Some(reason);
    }

    /// The reason the map is read-only, if it is.
    pub fn read_only(&self) -> Option<String> {
        let s = self.lock();
        s.damaged.clone().or_else(|| s.apply.as_ref().or(s.journal.as_ref()).map(|f| f.reason.clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_journal_failure_lets_one_probe_through_per_interval() {
        let f = Faults::new(Duration::from_millis(30));
        assert!(f.admit().is_ok());
        f.journal_failed("disk full".into());
        assert!(f.admit().unwrap_err().contains("disk full"));
        std::thread::sleep(Duration::from_millis(40));
        assert!(f.admit().is_ok(), "the probe");
        assert!(f.admit().is_err(), "only one probe per interval");
        f.journal_ok();
        assert!(f.admit().is_ok());
        assert_eq!(f.read_only(), None);
        f.apply_failed("io".into());
        assert!(f.apply_backing_off() && f.admit().is_err());
        f.apply_ok();
        f.set_damaged("corrupt block".into());
        assert_eq!(f.read_only().as_deref(), Some("corrupt block"));
    }
}
