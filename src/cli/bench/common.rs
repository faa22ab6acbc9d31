//! Helpers several benches share: percentiles, running a bench in a fresh process, temporary
//! directories and the length of a throughput run. Depends on no bench.

use anyhow::{Context, Result, bail};
use std::path::PathBuf;
#[cfg(feature = "server")]
use std::sync::atomic::{AtomicU64, Ordering};
#[cfg(feature = "server")]
use std::time::Duration;

/// Runs `bgkmap <args>` (this binary) in a fresh process and returns the JSON object it printed
/// last; its standard error becomes the error if it fails.
pub(super) fn bench_in_child(args: &[std::ffi::OsString]) -> Result<serde_json::Value> {
    let exe = std::env::current_exe().context("locating the bgkmap executable")?;
    let out = std::process::Command::new(exe)
        .args(args)
        .stdin(std::process::Stdio::null())
        .output()
        .with_context(|| format!("running {}", command_text(args)))?;
    if !out.status.success() {
        bail!(
            "{} failed ({}): {}",
            command_text(args),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let last = text.lines().rev().find(|l| l.trim_start().starts_with('{')).unwrap_or_default();
    serde_json::from_str(last).with_context(|| format!("{} printed no JSON object", command_text(args)))
}

/// `bgkmap` and `args` as one line, for messages.
pub(super) fn command_text(args: &[std::ffi::OsString]) -> String {
    let mut s = String::from("bgkmap");
    for a in args {
        s.push(' ');
        s.push_str(&a.to_string_lossy());
    }
    s
}

/// Nearest-rank percentile (sorts in place); NaN for an empty sample.
pub(super) fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let rank = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len());
    v[rank - 1]
}

/// A throughput run lasts until both: this much time in calls and this many calls.
#[cfg(feature = "server")]
pub(super) const MIN_BUSY: Duration = Duration::from_secs(1);
#[cfg(feature = "server")]
pub(super) const MIN_CALLS: usize = 5;

/// Removes a generated directory on the way out.
pub(super) struct Cleanup(pub(super) PathBuf);

impl Drop for Cleanup {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A fresh directory under the system temp dir, removed (with its contents) on drop.
#[cfg(feature = "server")]
#[derive(Debug)]
pub(super) struct TempDir(pub(super) PathBuf);

#[cfg(feature = "server")]
impl TempDir {
    pub(super) fn new() -> Result<Self> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let name = format!(
            "bgkmap-bench-server-{}-{nanos}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        );
        let path = std::env::temp_dir().join(name);
        std::fs::create_dir_all(std::env::temp_dir())?;
        std::fs::create_dir(&path).with_context(|| format!("{}: cannot create", path.display()))?;
        Ok(Self(path))
    }
}

#[cfg(feature = "server")]
impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A server for one bench run: gRPC and HTTP on free loopback ports, data in `data_dir`,
/// everything else at its defaults (callers override fields with `..loopback_server(dir)`).
#[cfg(feature = "server")]
pub(super) fn loopback_server(data_dir: PathBuf) -> crate::cli::serve::ServerConfig {
    let loopback = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
    crate::cli::serve::ServerConfig {
        data_dir,
        grpc_listen: loopback,
        http_listen: loopback,
        ..Default::default()
    }
}
