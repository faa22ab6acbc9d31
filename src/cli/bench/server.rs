//! `bgkmap bench server`: the map server in-process on loopback, driven through its own
//! transports (gRPC and HTTP JSON), with the in-process query as the reference. Measured figures
//! only; nothing here asserts on speed.

use super::common::{MIN_BUSY, MIN_CALLS, TempDir, loopback_server, percentile};
use super::world::random_direction;
use crate::api::pb;
use crate::cli::serve::{Running, runtime, start};
use crate::sim::{Lidar, SimScan, simulate};
use anyhow::{Context, Result, bail, ensure};
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::time::{Duration, Instant};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use tonic::transport::Channel;

#[derive(Debug, Args)]
pub struct ServerBenchArgs {
    /// Simulated scans streamed into map `bench` (built-in room, seed 0).
    #[arg(long, default_value_t = 24)]
    pub scans: usize,
    /// Points per gRPC QueryPoints request (and per in-process query) in the throughput run.
    #[arg(long, default_value_t = 100_000)]
    pub batch: usize,
    /// Sequential single-point QueryPoints calls per latency run (idle, then under ingest).
    #[arg(long, default_value_t = 2000)]
    pub latency_samples: usize,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

pub(super) const MAP: &str = "bench";
/// Interior of the simulated room (metres): x 0..10, y 0..12, z 0..3.
const ROOM: [f64; 3] = [10.0, 12.0, 3.0];
/// Rays per CastRays request and points per HTTP request.
const RAYS_PER_CALL: usize = 10_000;
const HTTP_POINTS_PER_CALL: usize = 10_000;
const RAY_RANGE_M: f64 = 8.0;
/// Distinct request payloads cycled through in a throughput run.
const DISTINCT_BATCHES: usize = 4;
/// Background ingest while measuring latency under ingest: one scan per period.
const BACKGROUND_PERIOD: Duration = Duration::from_millis(100);
pub(super) const MAX_MESSAGE: usize = 256 << 20;

pub(super) type Client = pb::map_service_client::MapServiceClient<Channel>;

pub fn run(a: ServerBenchArgs) -> Result<()> {
    let v = run_bench(&a)?;
    if a.json {
        println!("{v}");
    } else {
        println!("{}", summary(&v));
    }
    Ok(())
}

/// Runs the whole benchmark (server started and stopped here, in a temporary data directory)
/// and returns the JSON object `--json` prints.
pub fn run_bench(a: &ServerBenchArgs) -> Result<Value> {
    ensure!(a.scans > 0, "--scans must be > 0");
    ensure!(a.batch > 0, "--batch must be > 0");
    ensure!(a.latency_samples > 0, "--latency-samples must be > 0");
    // Declared before the runtime so it is removed after the server has stopped.
    let dir = TempDir::new()?;
    let config = loopback_server(dir.0.clone());
    let (_, sim) = simulate(0, a.scans, &Lidar::default());
    runtime()?.block_on(async {
        let running = start(&config).await?;
        let report = measure(&running, a, &sim).await;
        let stopped = running.shutdown().await;
        let report = report?;
        stopped?;
        Ok(report)
    })
}

/// The readable form of [`run_bench`]'s answer.
fn summary(v: &Value) -> String {
    let f = |key: &str| v[key].as_f64().unwrap_or(f64::NAN);
    let mega = |key: &str| f(key) / 1e6;
    format!(
        "server bench (in-process server on loopback, map of {} simulated scans):\n  \
         ingest (gRPC InsertScans stream): {:.1} scans/s, {:.3} M raw points/s\n  \
         gRPC QueryPoints, {} points per call: {:.2} M points/s\n  \
         gRPC QueryPoints, 1 point per call: p50 {:.0} µs, p99 {:.0} µs; under ingest \
         ({} background scans at ≤ 10/s): p50 {:.0} µs, p99 {:.0} µs\n  \
         gRPC CastRays, {RAYS_PER_CALL} rays of {RAY_RANGE_M} m per call: {:.3} M rays/s\n  \
         HTTP JSON query/points, {HTTP_POINTS_PER_CALL} points per request: {:.3} M points/s\n  \
         in-process query_points (1 thread), {} points per call: {:.2} M points/s",
        v["scans"],
        f("ingest_scans_per_s"),
        mega("ingest_points_per_s"),
        v["batch"],
        mega("grpc_points_per_s"),
        f("grpc_single_p50_us"),
        f("grpc_single_p99_us"),
        v["background_scans_under_ingest"],
        f("grpc_single_p50_us_under_ingest"),
        f("grpc_single_p99_us_under_ingest"),
        mega("grpc_rays_per_s"),
        mega("http_points_per_s"),
        v["batch"],
        mega("inprocess_points_per_s"),
    )
}

/// Every measurement against a running server, in order.
async fn measure(running: &Running, a: &ServerBenchArgs, sim: &[SimScan]) -> Result<Value> {
    let mut client = connect(running.grpc_addr).await?;
    let create = pb::CreateMapRequest { map: MAP.into(), params: Some(pb::MapParams::default()) };
    client.create_map(create).await.context("creating map bench")?;

    // Ingest: every scan over one client stream; the server answers once all are applied.
    let requests: Vec<pb::InsertScanRequest> =
        sim.iter().enumerate().map(|(i, s)| scan_request("bench-robot", i as u64 + 1, s)).collect();
    let raw_points: usize = sim.iter().map(|s| s.points_world.len()).sum();
    let t0 = Instant::now();
    let streamed =
        client.insert_scans(tokio_stream::iter(requests)).await.context("InsertScans")?.into_inner();
    let ingest_s = t0.elapsed().as_secs_f64();
    ensure!(
        streamed.applied == sim.len() as u64,
        "ingest applied {} of {} scans",
        streamed.applied,
        sim.len()
    );

    let mut rng = ChaCha8Rng::seed_from_u64(0x6267_6b6d);
    let grpc_points_per_s = grpc_points(&mut client, a.batch, &mut rng).await?;
    let (idle_p50, idle_p99) = {
        let mut us = single_point_latencies(&mut client, a.latency_samples, &mut rng).await?;
        (percentile(&mut us, 0.5), percentile(&mut us, 0.99))
    };
    let (busy_p50, busy_p99, background_scans) =
        latencies_under_ingest(running.grpc_addr, &mut client, a.latency_samples, sim, &mut rng).await?;
    let grpc_rays_per_s = grpc_rays(&mut client, &mut rng).await?;
    let http_points_per_s = http_points(running.http_addr, &mut rng).await?;
    let snap = running.service.snapshot(MAP)?;
    let batches = random_batches(a.batch, &mut rng);
    let inprocess_points_per_s = tokio::task::spawn_blocking(move || inprocess_points(&snap, &batches))
        .await
        .context("in-process query task")?;

    Ok(json!({
        "bench": "server",
        "scans": sim.len(), "batch": a.batch, "raw_points": raw_points,
        "ingest_scans_per_s": sim.len() as f64 / ingest_s,
        "ingest_points_per_s": raw_points as f64 / ingest_s,
        "grpc_points_per_s": grpc_points_per_s,
        "grpc_single_p50_us": idle_p50, "grpc_single_p99_us": idle_p99,
        "grpc_single_p50_us_under_ingest": busy_p50, "grpc_single_p99_us_under_ingest": busy_p99,
        "background_scans_under_ingest": background_scans,
        "grpc_rays_per_s": grpc_rays_per_s,
        "http_points_per_s": http_points_per_s,
        "inprocess_points_per_s": inprocess_points_per_s,
    }))
}

pub(super) async fn connect(addr: SocketAddr) -> Result<Client> {
    use crate::cli::serve::{GRPC_CONNECTION_WINDOW, GRPC_MAX_FRAME, GRPC_STREAM_WINDOW};
    let endpoint = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))?
        .tcp_nodelay(true)
        .initial_stream_window_size(GRPC_STREAM_WINDOW)
        .initial_connection_window_size(GRPC_CONNECTION_WINDOW)
        .max_frame_size(GRPC_MAX_FRAME);
    Ok(Client::connect(endpoint)
        .await
        .with_context(|| format!("connecting to gRPC {addr}"))?
        .max_decoding_message_size(MAX_MESSAGE)
        .max_encoding_message_size(MAX_MESSAGE))
}

fn scan_request(source: &str, seq: u64, s: &SimScan) -> pb::InsertScanRequest {
    pb::InsertScanRequest {
        map: MAP.into(),
        scan: Some(pb::Scan::world(source, seq, s.origin, &s.points_world)),
        // Ingest is measured end to end: acknowledged once integrated and stored.
        wait_applied: true,
    }
}

/// Calls counted and time spent inside them, for a throughput run.
#[derive(Debug, Default)]
pub(super) struct Meter {
    pub(super) calls: usize,
    pub(super) items: usize,
    pub(super) busy: Duration,
}

impl Meter {
    pub(super) fn done(&self) -> bool {
        self.calls >= MIN_CALLS && self.busy >= MIN_BUSY
    }

    pub(super) fn add(&mut self, items: usize, t0: Instant) {
        self.busy += t0.elapsed();
        self.calls += 1;
        self.items += items;
    }

    pub(super) fn per_s(&self) -> f64 {
        self.items as f64 / self.busy.as_secs_f64()
    }
}

fn random_point(rng: &mut ChaCha8Rng) -> [f64; 3] {
    ROOM.map(|extent| extent * rng.random::<f64>())
}

/// [`DISTINCT_BATCHES`] batches of `n` random points inside the room.
pub(super) fn random_batches(n: usize, rng: &mut ChaCha8Rng) -> Vec<Vec<[f64; 3]>> {
    (0..DISTINCT_BATCHES).map(|_| (0..n).map(|_| random_point(rng)).collect()).collect()
}

pub(super) fn xyz_f32(points: &[[f64; 3]]) -> Vec<u8> {
    points.iter().flat_map(|p| p.iter().flat_map(|&v| (v as f32).to_le_bytes())).collect()
}

pub(super) fn points_request(xyz: Vec<u8>) -> pb::QueryPointsRequest {
    pb::QueryPointsRequest { map: MAP.into(), xyz_f32: xyz, thresholds: None }
}

/// gRPC QueryPoints throughput, `batch` points per call (after one untimed call).
pub(super) async fn grpc_points(client: &mut Client, batch: usize, rng: &mut ChaCha8Rng) -> Result<f64> {
    let payloads: Vec<Vec<u8>> = random_batches(batch, rng).iter().map(|b| xyz_f32(b)).collect();
    let warm = client.query_points(points_request(payloads[0].clone())).await.context("QueryPoints")?;
    ensure!(warm.get_ref().probability.len() == batch, "QueryPoints answered the wrong number of points");
    let mut meter = Meter::default();
    for xyz in payloads.iter().cycle() {
        let req = points_request(xyz.clone());
        let t0 = Instant::now();
        let answer = client.query_points(req).await.context("QueryPoints")?;
        meter.add(answer.get_ref().probability.len(), t0);
        if meter.done() {
            break;
        }
    }
    Ok(meter.per_s())
}

/// Round-trip times (µs) of `n` sequential one-point QueryPoints calls.
async fn single_point_latencies(client: &mut Client, n: usize, rng: &mut ChaCha8Rng) -> Result<Vec<f64>> {
    let points: Vec<[f64; 3]> = (0..n).map(|_| random_point(rng)).collect();
    client.query_points(points_request(xyz_f32(&points[..1]))).await.context("QueryPoints")?;
    let mut us = Vec::with_capacity(n);
    for p in &points {
        let req = points_request(xyz_f32(std::slice::from_ref(p)));
        let t0 = Instant::now();
        client.query_points(req).await.context("QueryPoints")?;
        us.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    Ok(us)
}

/// Single-point latencies while another connection inserts a scan every [`BACKGROUND_PERIOD`]
/// (the simulated scans again, as source `bench-background` with fresh seq numbers):
/// (p50 µs, p99 µs, background scans applied).
async fn latencies_under_ingest(
    grpc: SocketAddr,
    client: &mut Client,
    n: usize,
    sim: &[SimScan],
    rng: &mut ChaCha8Rng,
) -> Result<(f64, f64, u64)> {
    let requests: Vec<pb::InsertScanRequest> =
        sim.iter().enumerate().map(|(i, s)| scan_request("bench-background", i as u64 + 1, s)).collect();
    let mut writer = connect(grpc).await?;
    let (stop, mut stopped) = tokio::sync::watch::channel(false);
    let background = tokio::spawn(async move {
        let mut tick = tokio::time::interval(BACKGROUND_PERIOD);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut applied = 0u64;
        for (round, template) in (0u64..).zip(requests.iter().cycle()) {
            tokio::select! {
                biased;
                _ = stopped.changed() => break,
                _ = tick.tick() => {}
            }
            let mut req = template.clone();
            if let Some(scan) = req.scan.as_mut() {
                scan.seq = round + 1;
            }
            if writer.insert_scan(req).await.context("background InsertScan")?.get_ref().applied {
                applied += 1;
            }
        }
        anyhow::Ok(applied)
    });
    let measured = single_point_latencies(client, n, rng).await;
    let _ = stop.send(true);
    let applied = background.await.context("background ingest task")?;
    let mut us = measured?;
    let applied = applied?;
    Ok((percentile(&mut us, 0.5), percentile(&mut us, 0.99), applied))
}

/// gRPC CastRays throughput: [`RAYS_PER_CALL`] rays of [`RAY_RANGE_M`] from random origins in
/// the room, in random directions.
async fn grpc_rays(client: &mut Client, rng: &mut ChaCha8Rng) -> Result<f64> {
    let batches: Vec<Vec<pb::Ray>> = (0..DISTINCT_BATCHES)
        .map(|_| {
            (0..RAYS_PER_CALL)
                .map(|_| pb::Ray {
                    origin: random_point(rng).to_vec(),
                    direction: random_direction(rng).to_vec(),
                    max_range: RAY_RANGE_M,
                })
                .collect()
        })
        .collect();
    let request = |rays: &Vec<pb::Ray>| pb::CastRaysRequest {
        map: MAP.into(),
        rays: rays.clone(),
        stop_at: pb::StopAt::Occupied as i32,
        thresholds: None,
    };
    let warm = client.cast_rays(request(&batches[0])).await.context("CastRays")?;
    ensure!(warm.get_ref().results.len() == RAYS_PER_CALL, "CastRays answered the wrong number of rays");
    let mut meter = Meter::default();
    for rays in batches.iter().cycle() {
        let req = request(rays);
        let t0 = Instant::now();
        let answer = client.cast_rays(req).await.context("CastRays")?;
        meter.add(answer.get_ref().results.len(), t0);
        if meter.done() {
            break;
        }
    }
    Ok(meter.per_s())
}

/// HTTP JSON `POST /v1/maps/bench/query/points` throughput over one keep-alive connection.
async fn http_points(http: SocketAddr, rng: &mut ChaCha8Rng) -> Result<f64> {
    let bodies: Vec<Vec<u8>> = random_batches(HTTP_POINTS_PER_CALL, rng)
        .iter()
        .map(|b| {
            let pts: Vec<[f32; 3]> = b.iter().map(|p| p.map(|v| v as f32)).collect();
            json!({ "points": pts }).to_string().into_bytes()
        })
        .collect();
    let path = format!("/v1/maps/{MAP}/query/points");
    let mut conn = HttpConnection::connect(http).await?;
    let warm = conn.post_json(&path, &bodies[0]).await?;
    let warm: Value = serde_json::from_slice(&warm).context("query/points: invalid JSON answer")?;
    let answered = warm["results"].as_array().map_or(0, Vec::len);
    ensure!(answered == HTTP_POINTS_PER_CALL, "query/points answered {answered} points");
    let mut meter = Meter::default();
    for body in bodies.iter().cycle() {
        let t0 = Instant::now();
        conn.post_json(&path, body).await?;
        meter.add(HTTP_POINTS_PER_CALL, t0);
        if meter.done() {
            break;
        }
    }
    Ok(meter.per_s())
}

/// The reference: [`crate::core::query::query_points`] on the service's snapshot, one thread.
fn inprocess_points(snap: &crate::service::Snapshot, batches: &[Vec<[f64; 3]>]) -> f64 {
    let th = snap.map.params().thresholds;
    let mut meter = Meter::default();
    for points in batches.iter().cycle() {
        let t0 = Instant::now();
        let answers = std::hint::black_box(crate::core::query::query_points(&snap.map, points, &th));
        meter.add(answers.len(), t0);
        if meter.done() {
            break;
        }
    }
    meter.per_s()
}

/// A minimal HTTP/1.1 client: one keep-alive connection, `Content-Length` bodies only.
#[derive(Debug)]
pub(super) struct HttpConnection {
    host: SocketAddr,
    stream: BufReader<TcpStream>,
}

/// Longest response head accepted.
const MAX_HEAD_BYTES: usize = 64 << 10;

impl HttpConnection {
    pub(super) async fn connect(host: SocketAddr) -> Result<Self> {
        let stream = TcpStream::connect(host).await.with_context(|| format!("connecting to HTTP {host}"))?;
        stream.set_nodelay(true)?;
        Ok(Self { host, stream: BufReader::new(stream) })
    }

    /// POSTs a JSON body; the response body, which must come with status 200.
    pub(super) async fn post_json(&mut self, path: &str, body: &[u8]) -> Result<Vec<u8>> {
        let head = format!(
            "POST {path} HTTP/1.1\r\nHost: {}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n",
            self.host,
            body.len()
        );
        let w = self.stream.get_mut();
        w.write_all(head.as_bytes()).await?;
        w.write_all(body).await?;
        w.flush().await?;

        let mut line = String::new();
        let mut head_bytes = 0;
        let mut status = None;
        let mut length = None;
        loop {
            line.clear();
            let n = self.stream.read_line(&mut line).await.context("reading the HTTP response")?;
            ensure!(n > 0, "HTTP connection closed by the server");
            head_bytes += n;
            ensure!(head_bytes <= MAX_HEAD_BYTES, "HTTP response head longer than {MAX_HEAD_BYTES} bytes");
            let text = line.trim_end_matches(['\r', '\n']);
            if status.is_none() {
                let code = text
                    .strip_prefix("HTTP/1.1 ")
                    .and_then(|r| r.get(..3))
                    .and_then(|c| c.parse::<u16>().ok());
                status = Some(code.with_context(|| format!("bad HTTP status line {text:?}"))?);
                continue;
            }
            if text.is_empty() {
                break;
            }
            let Some((name, value)) = text.split_once(':') else { bail!("bad HTTP header line {text:?}") };
            if name.eq_ignore_ascii_case("content-length") {
                length = Some(value.trim().parse::<usize>().context("bad Content-Length")?);
            } else if name.eq_ignore_ascii_case("transfer-encoding") {
                bail!(
                    "HTTP response with Transfer-Encoding {:?} (only Content-Length is read)",
                    value.trim()
                );
            }
        }
        let length = length.context("HTTP response without Content-Length")?;
        let mut answer = vec![0; length];
        self.stream.read_exact(&mut answer).await.context("reading the HTTP response body")?;
        if status != Some(200) {
            bail!("POST {path}: HTTP {status:?}: {}", String::from_utf8_lossy(&answer));
        }
        Ok(answer)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiny_server_bench_reports_every_figure() {
        let a = ServerBenchArgs { scans: 2, batch: 1000, latency_samples: 20, json: true };
        let v = run_bench(&a).unwrap();
        for key in [
            "ingest_scans_per_s",
            "ingest_points_per_s",
            "grpc_points_per_s",
            "grpc_single_p50_us",
            "grpc_single_p99_us",
            "grpc_single_p50_us_under_ingest",
            "grpc_single_p99_us_under_ingest",
            "grpc_rays_per_s",
            "http_points_per_s",
            "inprocess_points_per_s",
            "batch",
            "scans",
        ] {
            let x = v[key].as_f64().unwrap_or_else(|| panic!("{key} missing in {v}"));
            assert!(x.is_finite() && x > 0.0, "{key} = {x}");
        }
        assert_eq!(v["batch"], 1000);
        assert_eq!(v["scans"], 2);
    }
}
