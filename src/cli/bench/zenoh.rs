//! `bgkmap bench zenoh`: the server in-process with its zenoh session on loopback, driven by
//! zenoh peers of its own: scans per second put by several publishers at once, and point-query
//! throughput over zenoh next to gRPC on the same server and payloads. Measured figures only.

use super::common::{TempDir, loopback_server};
use super::server::{MAP, Meter, connect, grpc_points, points_request, random_batches, xyz_f32};
use crate::api::pb;
use crate::api::zenoh::ZenohConfig;
use crate::cli::serve::{Running, ServerConfig, runtime, start};
use crate::sim::{Lidar, SimScan, simulate};
use anyhow::{Context, Result, bail, ensure};
use clap::Args;
use prost::Message as _;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::time::{Duration, Instant};
use zenoh::Wait as _;
use zenoh::qos::CongestionControl;

#[derive(Debug, Args)]
pub struct ZenohBenchArgs {
    /// Simulated scans (built-in room, seed 0), shared round-robin among the publishers.
    #[arg(long, default_value_t = 24)]
    pub scans: usize,
    /// Publishers putting scans at the same time, each its own zenoh peer.
    #[arg(long, default_value_t = 3)]
    pub publishers: usize,
    /// Points per query, over zenoh and over gRPC.
    #[arg(long, default_value_t = 100_000)]
    pub batch: usize,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// Longest wait for the ingest to finish or a subscriber to match.
const TIMEOUT: Duration = Duration::from_secs(600);

pub fn run(a: ZenohBenchArgs) -> Result<()> {
    let v = run_bench(&a)?;
    if a.json {
        println!("{v}");
    } else {
        let f = |k: &str| v[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "zenoh bench (in-process server, zenoh peers on loopback, {} simulated scans):\n  \
             ingest, {} publishers putting at once: {:.1} scans/s journaled (durable), \
             {:.1} scans/s integrated, {:.3} M raw points/s integrated\n  \
             query/points over zenoh, {} points per query: {:.2} M points/s\n  \
             QueryPoints over gRPC, same server and payloads: {:.2} M points/s",
            v["scans"],
            v["publishers"],
            f("journaled_scans_per_s"),
            f("ingest_scans_per_s"),
            f("ingest_points_per_s") / 1e6,
            v["batch"],
            f("zenoh_points_per_s") / 1e6,
            f("grpc_points_per_s") / 1e6,
        );
    }
    Ok(())
}

/// Runs the benchmark (server started and stopped here, temporary data directory).
pub fn run_bench(a: &ZenohBenchArgs) -> Result<Value> {
    ensure!(a.scans > 0 && a.publishers > 0 && a.batch > 0, "--scans, --publishers and --batch must be > 0");
    let dir = TempDir::new()?;
    let config = ServerConfig {
        zenoh: ZenohConfig { enabled: true, listen: vec!["tcp/127.0.0.1:0".into()], ..Default::default() },
        ..loopback_server(dir.0.clone())
    };
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

/// A zenoh peer of the benchmark's own, connected to the server.
pub(super) fn peer(locator: &str) -> Result<zenoh::Session> {
    let mut c = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", "false".into()),
        ("listen/endpoints", "[]".into()),
        ("connect/endpoints", format!("[\"{locator}\"]")),
    ] {
        c.insert_json5(key, &value).map_err(|e| anyhow::anyhow!("zenoh config {key}: {e}"))?;
    }
    zenoh::open(c).wait().map_err(|e| anyhow::anyhow!("opening a zenoh peer: {e}"))
}

async fn measure(running: &Running, a: &ZenohBenchArgs, sim: &[SimScan]) -> Result<Value> {
    let locator = running.zenoh_locators.first().context("the server has no zenoh locator")?.clone();
    let mut client = connect(running.grpc_addr).await?;
    let create = pb::CreateMapRequest { map: MAP.into(), params: Some(pb::MapParams::default()) };
    client.create_map(create).await.context("creating map bench")?;
    // Publishers are threads of their own; the server's scan worker needs no async worker.
    let (journaled_s, ingest_s) =
        tokio::task::block_in_place(|| ingest(running, &locator, a.publishers, sim))?;
    let raw_points: usize = sim.iter().map(|s| s.points_world.len()).sum();
    let session = peer(&locator)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0x6267_6b6d);
    let zenoh_points_per_s = zenoh_points(&session, a.batch, &mut rng).await?;
    let grpc_points_per_s = grpc_points(&mut client, a.batch, &mut rng).await?;
    let _ = session.close().await;
    Ok(json!({
        "bench": "zenoh",
        "scans": sim.len(), "publishers": a.publishers, "batch": a.batch, "raw_points": raw_points,
        "journaled_scans_per_s": sim.len() as f64 / journaled_s,
        "ingest_scans_per_s": sim.len() as f64 / ingest_s,
        "ingest_points_per_s": raw_points as f64 / ingest_s,
        "zenoh_points_per_s": zenoh_points_per_s,
        "grpc_points_per_s": grpc_points_per_s,
    }))
}

/// Seconds from the first put until every scan is journaled, and until every scan is
/// integrated, `publishers` peers putting their share at once (each waits until the server's
/// subscriber matches before the clock starts). Blocks the calling thread.
fn ingest(running: &Running, locator: &str, publishers: usize, sim: &[SimScan]) -> Result<(f64, f64)> {
    let shares: Vec<Vec<Vec<u8>>> = (0..publishers)
        .map(|p| {
            let source = format!("robot{}", p + 1);
            let mine = sim.iter().enumerate().filter(|(i, _)| i % publishers == p);
            mine.map(|(i, s)| {
                pb::Scan::world(&source, i as u64 + 1, s.origin, &s.points_world).encode_to_vec()
            })
            .collect()
        })
        .collect();
    // Everyone starts together; sessions stay open until the map has every scan (closing right
    // after the puts may drop some still queued).
    let (ready, done) = (std::sync::Barrier::new(publishers + 1), std::sync::Barrier::new(publishers + 1));
    let service = running.service.clone();
    std::thread::scope(|scope| -> Result<(f64, f64)> {
        let handles: Vec<_> = shares
            .iter()
            .enumerate()
            .map(|(p, share)| {
                let (ready, done) = (&ready, &done);
                scope.spawn(move || -> Result<()> {
                    // Every thread reaches both barriers, also when it fails.
                    let setup = publisher(locator, p);
                    ready.wait();
                    let sent = setup.and_then(|(session, publisher)| {
                        for scan in share {
                            publisher.put(scan.clone()).wait().map_err(|e| anyhow::anyhow!("put: {e}"))?;
                        }
                        Ok(session)
                    });
                    done.wait();
                    let _ = sent?.close().wait();
                    Ok(())
                })
            })
            .collect();
        ready.wait();
        let t0 = Instant::now();
        let finished = wait_ingested(&service, sim.len() as u64, t0);
        done.wait();
        for h in handles {
            h.join().map_err(|_| anyhow::anyhow!("a publisher panicked"))??;
        }
        finished
    })
}

/// Seconds from `t0` until `want` scans are journaled (acknowledged, durable) and until they
/// are integrated (map version).
fn wait_ingested(service: &crate::service::MapService, want: u64, t0: Instant) -> Result<(f64, f64)> {
    let mut journaled = None;
    loop {
        let info = service.map_info(MAP)?;
        if journaled.is_none() && info.sources.values().map(|s| s.received).sum::<u64>() >= want {
            journaled = Some(t0.elapsed().as_secs_f64());
        }
        if let Some(j) = journaled
            && info.version >= want
        {
            return Ok((j, t0.elapsed().as_secs_f64()));
        }
        ensure!(t0.elapsed() < TIMEOUT, "ingest over zenoh did not finish: {info:?}");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Publisher `p`'s session and its publisher on `bgkmap/bench/scans/robot<p+1>` (congestion
/// control Block: nothing is dropped), once the server's subscriber matches.
fn publisher(locator: &str, p: usize) -> Result<(zenoh::Session, zenoh::pubsub::Publisher<'static>)> {
    let session = peer(locator)?;
    let key = format!("bgkmap/{MAP}/scans/robot{}", p + 1);
    let publisher = session
        .declare_publisher(key)
        .congestion_control(CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let deadline = Instant::now() + TIMEOUT;
    while !publisher.matching_status().wait().map_err(|e| anyhow::anyhow!("{e}"))?.matching() {
        ensure!(Instant::now() < deadline, "the server's scan subscriber never matched");
        std::thread::sleep(Duration::from_millis(5));
    }
    Ok((session, publisher))
}

/// zenoh `query/points` throughput, `batch` points per query (after one untimed query).
async fn zenoh_points(session: &zenoh::Session, batch: usize, rng: &mut ChaCha8Rng) -> Result<f64> {
    let key = format!("bgkmap/{MAP}/query/points");
    let querier = session
        .declare_querier(&key)
        .timeout(Duration::from_secs(60))
        .await
        .map_err(|e| anyhow::anyhow!("declaring a querier on {key}: {e}"))?;
    let payloads: Vec<Vec<u8>> =
        random_batches(batch, rng).iter().map(|b| points_request(xyz_f32(b)).encode_to_vec()).collect();
    let ask = |payload: Vec<u8>| async {
        let replies = querier.get().payload(payload).await.map_err(|e| anyhow::anyhow!("get {key}: {e}"))?;
        let reply = replies.recv_async().await.map_err(|_| anyhow::anyhow!("no reply on {key}"))?;
        match reply.result() {
            Ok(sample) => {
                Ok(crate::api::codec::decode::<pb::QueryPointsResponse>(&sample.payload().to_bytes())?
                    .probability
                    .len())
            }
            Err(e) => bail!("{key}: {}", e.payload().try_to_string().unwrap_or_default()),
        }
    };
    ensure!(ask(payloads[0].clone()).await? == batch, "query/points answered the wrong number of points");
    let mut meter = Meter::default();
    for payload in payloads.iter().cycle() {
        let t0 = Instant::now();
        let n = ask(payload.clone()).await?;
        meter.add(n, t0);
        if meter.done() {
            break;
        }
    }
    Ok(meter.per_s())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiny_zenoh_bench_reports_every_figure() {
        let a = ZenohBenchArgs { scans: 3, publishers: 3, batch: 1000, json: true };
        let v = run_bench(&a).unwrap();
        for key in [
            "journaled_scans_per_s",
            "ingest_scans_per_s",
            "ingest_points_per_s",
            "zenoh_points_per_s",
            "grpc_points_per_s",
        ] {
            let x = v[key].as_f64().unwrap_or_else(|| panic!("{key} missing in {v}"));
            assert!(x.is_finite() && x > 0.0, "{key} = {x}");
        }
        assert_eq!((v["scans"].as_u64(), v["publishers"].as_u64()), (Some(3), Some(3)));
    }
}
