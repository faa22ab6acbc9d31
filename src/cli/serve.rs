//! `bgkmap serve`: the long-running map server (gRPC and HTTP on loopback by default).
//!
//! Configuration comes from compiled-in defaults, then a TOML file (`--config`), then the
//! environment (`BGKMAP_*`), then flags — parsed once into a [`ServerConfig`].

use crate::api::grpc::{GrpcConfig, routes};
use crate::api::http::{HttpConfig, router};
use crate::api::zenoh::{ZenohConfig, ZenohMode};
use crate::service::{MapService, QueryLimits, ScanLimits, ServiceConfig};
use crate::store::Retention;
use anyhow::{Context, Result};
use clap::Args;
use serde::Deserialize;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

/// Every setting of the server. TOML keys are the field names.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServerConfig {
    /// Directory holding one `<map>.bgkmap` file per map. Default `bgkmap-data`.
    pub data_dir: PathBuf,
    /// gRPC listen address. Default `127.0.0.1:50051` (loopback only).
    pub grpc_listen: SocketAddr,
    /// HTTP listen address. Default `127.0.0.1:8080` (loopback only).
    pub http_listen: SocketAddr,
    /// Scans queued per map to be journaled before ingest answers RESOURCE_EXHAUSTED / 429.
    /// Default 64.
    pub queue_capacity: usize,
    /// Journaled scans per map waiting for integration before ingest answers busy. Default 256.
    pub max_unapplied_scans: usize,
    /// Raw scans kept in each map's journal: `all` (default), `none`, an age (`7d`) or a size
    /// (`2GiB`).
    pub journal_retention: String,
    /// Milliseconds before writing is retried after a failed write. Default 1000.
    pub write_retry_ms: u64,
    /// Threads integrating scans (a batch one scan per thread, a lone scan split). Default 1.
    pub threads_per_scan: usize,
    /// Most points per scan. Default 4194304.
    pub max_points: usize,
    /// Largest box query in lattice positions. Default 4000000.
    pub max_box_cells: u64,
    /// Largest request message / body in bytes. Default 67108864 (64 MiB).
    pub max_message_bytes: usize,
    /// The zenoh session (table `[zenoh]`). Default off.
    pub zenoh: ZenohConfig,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            data_dir: PathBuf::from("bgkmap-data"),
            grpc_listen: SocketAddr::from(([127, 0, 0, 1], 50051)),
            http_listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            queue_capacity: 64,
            max_unapplied_scans: 256,
            journal_retention: "all".into(),
            write_retry_ms: 1000,
            threads_per_scan: 1,
            max_points: 4 << 20,
            max_box_cells: 4_000_000,
            max_message_bytes: 64 << 20,
            zenoh: ZenohConfig::default(),
        }
    }
}

#[derive(Debug, Args)]
pub struct ServeArgs {
    /// TOML configuration file (keys as in `deploy/bgkmap.toml`).
    #[arg(long, env = "BGKMAP_CONFIG")]
    pub config: Option<PathBuf>,
    /// Directory of map files.
    #[arg(long, env = "BGKMAP_DATA_DIR")]
    pub data_dir: Option<PathBuf>,
    /// gRPC listen address (port 0 picks a free port; the bound address is printed).
    #[arg(long, env = "BGKMAP_GRPC_LISTEN")]
    pub grpc_listen: Option<SocketAddr>,
    /// HTTP listen address (port 0 picks a free port; the bound address is printed).
    #[arg(long, env = "BGKMAP_HTTP_LISTEN")]
    pub http_listen: Option<SocketAddr>,
    /// Scans queued per map before ingest is refused as busy.
    #[arg(long, env = "BGKMAP_QUEUE_CAPACITY")]
    pub queue_capacity: Option<usize>,
    /// Largest box query in lattice positions.
    #[arg(long, env = "BGKMAP_MAX_BOX_CELLS")]
    pub max_box_cells: Option<u64>,
    /// Raw scans kept in each map's journal: all, none, an age (7d, 12h) or a size (2GiB).
    #[arg(long, env = "BGKMAP_JOURNAL_RETENTION")]
    pub journal_retention: Option<String>,
    /// Milliseconds before writing is retried after a failed write (disk full).
    #[arg(long, env = "BGKMAP_WRITE_RETRY_MS")]
    pub write_retry_ms: Option<u64>,
    #[command(flatten)]
    pub zenoh: ZenohArgs,
}

/// zenoh flags; any of them turns the session on.
#[derive(Debug, Default, Args)]
pub struct ZenohArgs {
    /// Open the zenoh session (peer on tcp/127.0.0.1:7450 unless configured otherwise).
    #[arg(long = "zenoh", env = "BGKMAP_ZENOH")]
    pub enabled: bool,
    /// zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7450 (repeatable; replaces the
    /// configured ones; port 0 picks a free port).
    #[arg(
        long = "zenoh-listen",
        env = "BGKMAP_ZENOH_LISTEN",
        value_name = "ENDPOINT",
        value_delimiter = ','
    )]
    pub listen: Vec<String>,
    /// zenoh endpoint to connect to: a peer or a router, e.g. tcp/127.0.0.1:7447 (repeatable).
    #[arg(
        long = "zenoh-connect",
        env = "BGKMAP_ZENOH_CONNECT",
        value_name = "ENDPOINT",
        value_delimiter = ','
    )]
    pub connect: Vec<String>,
    /// zenoh session mode.
    #[arg(long = "zenoh-mode", env = "BGKMAP_ZENOH_MODE")]
    pub mode: Option<ZenohMode>,
}

impl ZenohArgs {
    fn apply(&self, c: &mut ZenohConfig) {
        if !self.listen.is_empty() {
            c.listen = self.listen.clone();
        }
        if !self.connect.is_empty() {
            c.connect = self.connect.clone();
        }
        if let Some(m) = self.mode {
            c.mode = m;
        }
        c.enabled |=
            self.enabled || !self.listen.is_empty() || !self.connect.is_empty() || self.mode.is_some();
    }
}

impl ServeArgs {
    /// Defaults, then the file, then environment and flags (clap reads both).
    pub fn resolve(&self) -> Result<ServerConfig> {
        let mut c = match &self.config {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("{}: cannot read", path.display()))?;
                toml::from_str(&text).with_context(|| format!("{}: invalid configuration", path.display()))?
            }
            None => ServerConfig::default(),
        };
        if let Some(v) = &self.data_dir {
            c.data_dir = v.clone();
        }
        if let Some(v) = self.grpc_listen {
            c.grpc_listen = v;
        }
        if let Some(v) = self.http_listen {
            c.http_listen = v;
        }
        if let Some(v) = self.queue_capacity {
            c.queue_capacity = v;
        }
        if let Some(v) = self.max_box_cells {
            c.max_box_cells = v;
        }
        if let Some(v) = &self.journal_retention {
            c.journal_retention = v.clone();
        }
        if let Some(v) = self.write_retry_ms {
            c.write_retry_ms = v;
        }
        c.journal_retention.parse::<Retention>().map_err(anyhow::Error::msg)?;
        self.zenoh.apply(&mut c.zenoh);
        anyhow::ensure!(c.queue_capacity > 0, "queue_capacity must be > 0");
        anyhow::ensure!(c.threads_per_scan > 0, "threads_per_scan must be > 0");
        if c.zenoh.enabled {
            c.zenoh.validate().map_err(anyhow::Error::msg)?;
        }
        Ok(c)
    }
}

/// A running server: its bound addresses and the service behind them.
#[derive(Debug)]
pub struct Running {
    pub grpc_addr: SocketAddr,
    pub http_addr: SocketAddr,
    pub service: Arc<MapService>,
    /// The zenoh session's listening locators (empty without zenoh or in client mode).
    pub zenoh_locators: Vec<String>,
    /// The zenoh transport, when enabled.
    #[cfg(feature = "zenoh")]
    pub zenoh: Option<crate::api::zenoh::ZenohTransport>,
    tasks: Vec<tokio::task::JoinHandle<Result<()>>>,
    stop: tokio::sync::watch::Sender<bool>,
}

impl Running {
    /// Stops accepting requests, finishes those in flight, drains every map's queue.
    pub async fn shutdown(self) -> Result<()> {
        let _ = self.stop.send(true);
        // Change streams (gRPC WatchUpdates, HTTP SSE) never end by themselves; end them so
        // the graceful shutdown does not wait for their connections forever.
        self.service.close_updates();
        #[cfg(feature = "zenoh")]
        if let Some(z) = self.zenoh {
            z.shutdown().await;
        }
        for t in self.tasks {
            t.await.context("server task panicked")??;
        }
        let service = self.service;
        tokio::task::spawn_blocking(move || service.shutdown()).await?;
        Ok(())
    }
}

/// Opens the data directory, binds both listeners and starts serving.
pub async fn start(c: &ServerConfig) -> Result<Running> {
    #[cfg(not(feature = "zenoh"))]
    anyhow::ensure!(!c.zenoh.enabled, "zenoh is enabled but this bgkmap was built without the zenoh feature");
    let service_config = ServiceConfig {
        queue_capacity: c.queue_capacity,
        threads_per_scan: c.threads_per_scan,
        limits: ScanLimits { max_points: c.max_points, ..ScanLimits::default() },
        queries: QueryLimits { max_box_cells: c.max_box_cells },
        max_unapplied_scans: c.max_unapplied_scans.max(1),
        retention: c.journal_retention.parse::<Retention>().map_err(anyhow::Error::msg)?,
        write_retry: std::time::Duration::from_millis(c.write_retry_ms),
        ..ServiceConfig::default()
    };
    let dir = c.data_dir.clone();
    let service = Arc::new(
        tokio::task::spawn_blocking(move || MapService::open(&dir, service_config))
            .await?
            .with_context(|| format!("opening data directory {}", c.data_dir.display()))?,
    );
    let grpc_listener = tokio::net::TcpListener::bind(c.grpc_listen)
        .await
        .with_context(|| format!("binding gRPC to {}", c.grpc_listen))?;
    let http_listener = tokio::net::TcpListener::bind(c.http_listen)
        .await
        .with_context(|| format!("binding HTTP to {}", c.http_listen))?;
    let (grpc_addr, http_addr) = (grpc_listener.local_addr()?, http_listener.local_addr()?);
    let (stop, stop_rx) = tokio::sync::watch::channel(false);
    let stopped = move |mut rx: tokio::sync::watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|s| *s).await;
    };
    let grpc_config = GrpcConfig { max_message_bytes: c.max_message_bytes };
    let grpc_routes = routes(service.clone(), grpc_config).await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let grpc = tokio::spawn({
        let rx = stop_rx.clone();
        async move {
            tonic::transport::Server::builder()
                .initial_stream_window_size(GRPC_STREAM_WINDOW)
                .initial_connection_window_size(GRPC_CONNECTION_WINDOW)
                .max_frame_size(GRPC_MAX_FRAME)
                .add_routes(grpc_routes)
                .serve_with_incoming_shutdown(incoming_nodelay(grpc_listener), stopped(rx))
                .await
                .context("gRPC server")
        }
    });
    let http_config = HttpConfig { max_body_bytes: c.max_message_bytes };
    let app = router(service.clone(), http_config);
    let http = tokio::spawn(async move {
        axum::serve(http_listener, app).with_graceful_shutdown(stopped(stop_rx)).await.context("HTTP server")
    });
    let tasks = vec![grpc, http];
    #[cfg(feature = "zenoh")]
    {
        let zenoh = match c.zenoh.enabled {
            false => None,
            true => {
                let calls = crate::api::proto::calls::ProtoCalls::new(service.clone(), c.max_message_bytes);
                let started = crate::api::zenoh::ZenohTransport::start(calls, &c.zenoh).await;
                Some(started.context("starting zenoh")?)
            }
        };
        let zenoh_locators = zenoh.as_ref().map(|z| z.locators().to_vec()).unwrap_or_default();
        Ok(Running { grpc_addr, http_addr, service, zenoh_locators, zenoh, tasks, stop })
    }
    #[cfg(not(feature = "zenoh"))]
    Ok(Running { grpc_addr, http_addr, service, zenoh_locators: Vec::new(), tasks, stop })
}

/// HTTP/2 flow-control windows the gRPC server grants its peers (bytes). hyper's 1 MiB default
/// makes a 100k-point query (1.2 MB of points) wait a round trip for a window update
/// mid-request; a window as large as the biggest message streams it in one go.
pub const GRPC_STREAM_WINDOW: u32 = 16 << 20;
/// Connection-wide window: room for two full-size requests in flight at once.
pub const GRPC_CONNECTION_WINDOW: u32 = 32 << 20;
/// Largest HTTP/2 frame we accept from a peer (the 16 KiB default cuts a 1.2 MB request into 75
/// frames). Our answers' frames are bounded by what each client accepts: the bench clients ask
/// for the same 1 MiB, clients that keep the default get 16 KiB frames.
pub const GRPC_MAX_FRAME: u32 = 1 << 20;

/// Accepted connections with Nagle's algorithm off: small answers (single-point queries) must
/// not wait for the peer's delayed ACK.
fn incoming_nodelay(
    listener: tokio::net::TcpListener,
) -> impl tokio_stream::Stream<Item = std::io::Result<tokio::net::TcpStream>> {
    use tokio_stream::StreamExt as _;
    tokio_stream::wrappers::TcpListenerStream::new(listener).map(|conn| {
        if let Ok(c) = &conn {
            let _ = c.set_nodelay(true);
        }
        conn
    })
}

/// A future that resolves when SIGINT or SIGTERM arrives. The handlers are installed when this
/// is called, not when the future is first polled: callers install them before they announce
/// that they are ready, so a supervisor's SIGTERM that follows the announcement is always a
/// graceful shutdown, never the default (immediate) death.
pub fn shutdown_signal() -> impl std::future::Future<Output = ()> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let streams = signal(SignalKind::interrupt()).and_then(|i| Ok((i, signal(SignalKind::terminate())?)));
        async move {
            match streams {
                Ok((mut int, mut term)) => {
                    tokio::select! {
                        _ = int.recv() => {}
                        _ = term.recv() => {}
                    }
                }
                Err(e) => {
                    eprintln!("bgkmap: cannot install signal handlers ({e}); waiting for Ctrl-C only");
                    let _ = tokio::signal::ctrl_c().await;
                }
            }
        }
    }
    #[cfg(not(unix))]
    async {
        let _ = tokio::signal::ctrl_c().await;
    }
}

pub fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("bgkmap-io")
        .build()
        .context("tokio runtime")
}

pub fn run(a: ServeArgs) -> Result<()> {
    let config = a.resolve()?;
    runtime()?.block_on(async {
        let running = start(&config).await?;
        let stop = shutdown_signal();
        // zenoh first: test harnesses read lines until both gRPC and HTTP are reported.
        for l in &running.zenoh_locators {
            println!("zenoh listening on {l}");
        }
        println!("grpc listening on {}", running.grpc_addr);
        println!("http listening on {}", running.http_addr);
        println!("data directory {}", config.data_dir.display());
        use std::io::Write as _;
        let _ = std::io::stdout().flush();
        stop.await;
        eprintln!("bgkmap: shutting down (draining queues)");
        running.shutdown().await
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_config_documents_every_key_with_its_default() {
        let text = include_str!("../../deploy/bgkmap.toml");
        let parsed: ServerConfig = toml::from_str(text).unwrap();
        let d = ServerConfig::default();
        assert_eq!(parsed.data_dir, d.data_dir);
        assert_eq!((parsed.grpc_listen, parsed.http_listen), (d.grpc_listen, d.http_listen));
        assert_eq!((parsed.queue_capacity, parsed.threads_per_scan), (d.queue_capacity, d.threads_per_scan));
        assert_eq!(
            (parsed.max_points, parsed.max_box_cells, parsed.max_message_bytes),
            (d.max_points, d.max_box_cells, d.max_message_bytes)
        );
        assert_eq!(
            (parsed.max_unapplied_scans, &parsed.journal_retention, parsed.write_retry_ms),
            (d.max_unapplied_scans, &d.journal_retention, d.write_retry_ms)
        );
        assert_eq!(parsed.zenoh, d.zenoh);
        assert!(toml::from_str::<ServerConfig>("bogus = 1").is_err(), "unknown keys are refused");
    }

    #[test]
    fn flags_override_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.toml");
        std::fs::write(&path, "queue_capacity = 7\nmax_box_cells = 10\n").unwrap();
        let args = ServeArgs {
            config: Some(path),
            data_dir: None,
            grpc_listen: None,
            http_listen: None,
            queue_capacity: Some(3),
            max_box_cells: None,
            journal_retention: Some("7d".into()),
            write_retry_ms: None,
            zenoh: ZenohArgs { connect: vec!["tcp/127.0.0.1:7447".into()], ..ZenohArgs::default() },
        };
        let c = args.resolve().unwrap();
        assert_eq!((c.queue_capacity, c.max_box_cells), (3, 10));
        assert!(c.zenoh.enabled, "a zenoh endpoint flag turns zenoh on");
        assert_eq!((c.zenoh.connect.len(), c.zenoh.listen.len()), (1, 1));
        assert_eq!(c.journal_retention.parse::<Retention>(), Ok(Retention::MaxAgeSeconds(7 * 86_400)));
        let bad = ServeArgs { journal_retention: Some("7 weeks".into()), ..args };
        assert!(bad.resolve().unwrap_err().to_string().contains("unknown unit"));
    }
}
