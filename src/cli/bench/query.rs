//! `bgkmap bench query`: query speed on a large map (the outdoor drive of [`super::world`],
//! well over a million cells with evidence), in-process and through every transport, with the
//! same seeded workload: batched points, single-point latency, 1 m and 10 m boxes, 8 m and 30 m
//! rays. Each transport (in-process, gRPC, HTTP, zenoh) is one [`QueryTransport`] (in [`super::query_net`]). Measured
//! figures only; nothing asserts speed.

use super::common::{MIN_BUSY, MIN_CALLS, TempDir, loopback_server, percentile};
use super::query_net::{Grpc, Http, InProcess, MAP, QueryTransport, Zenoh, latencies_under_ingest};
use super::world::{Workload, build_map, outdoor_params, outdoor_scans};
use crate::api::zenoh::ZenohConfig;
use crate::cli::serve::{ServerConfig, runtime, start};
use crate::sim::SimScan;
use anyhow::{Result, ensure};
use clap::Args;
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct QueryBenchArgs {
    /// Scans of the outdoor drive that build the map (4 give about 6M cells with evidence).
    #[arg(long, default_value_t = 4)]
    pub scans: usize,
    /// Points per batched point query.
    #[arg(long, default_value_t = 100_000)]
    pub batch: usize,
    /// Single-point queries per latency run.
    #[arg(long, default_value_t = 2000)]
    pub latency_samples: usize,
    /// Rays per ray query.
    #[arg(long, default_value_t = 10_000)]
    pub rays: usize,
    /// Threads integrating the map (building it is not measured).
    #[arg(long, default_value_t = 2)]
    pub build_threads: usize,
    /// Measure the core's queries only (no server, no network transports).
    #[arg(long)]
    pub in_process_only: bool,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

/// A call a throughput run repeats.
#[derive(Debug, Clone, Copy)]
enum Op {
    Points,
    /// Rays of length kind `k`.
    Rays(usize),
}

/// Repeats `op` over the workload's distinct payloads until [`MIN_BUSY`] and [`MIN_CALLS`]
/// (after one untimed call); items per second of the median call, so a call the host's other
/// tenants slowed down moves the figure no more than one that ran alone.
async fn throughput<T: QueryTransport>(t: &mut T, w: &Workload, op: Op) -> Result<f64> {
    let distinct = match op {
        Op::Points => w.point_batches.len(),
        Op::Rays(k) => w.rays[k].1.len(),
    };
    let once = async |t: &mut T, i: usize| match op {
        Op::Points => t.points(w, i % distinct).await,
        Op::Rays(k) => t.rays(w, k, i % distinct).await,
    };
    once(t, 0).await?;
    let (mut rates, mut busy) = (Vec::new(), Duration::ZERO);
    while rates.len() < MIN_CALLS || busy < MIN_BUSY {
        let t0 = Instant::now();
        let items = once(t, rates.len()).await?;
        let dt = t0.elapsed();
        busy += dt;
        rates.push(items as f64 / dt.as_secs_f64());
    }
    Ok(percentile(&mut rates, 0.5))
}

/// Every figure of one transport.
pub(super) async fn measure<T: QueryTransport>(t: &mut T, w: &Workload) -> Result<Value> {
    let points_per_s = throughput(t, w, Op::Points).await?;
    let mut us = Vec::with_capacity(w.singles.len());
    t.single(w, 0).await?;
    for i in 0..w.singles.len() {
        let t0 = Instant::now();
        t.single(w, i).await?;
        us.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    let mut v = json!({"transport": t.name(), "points_per_s": points_per_s, "batch": w.point_batches[0].len(),
                       "single_p50_us": percentile(&mut us, 0.5), "single_p99_us": percentile(&mut us, 0.99)});
    for (kind, (edge, list)) in w.boxes.iter().enumerate() {
        let mut ms = Vec::new();
        let mut cells = 0;
        for i in 0..list.len() {
            let t0 = Instant::now();
            cells += t.boxed(w, kind, i).await?;
            ms.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        v[format!("box_{edge}m_ms_median")] = json!(percentile(&mut ms, 0.5));
        v[format!("box_{edge}m_cells_mean")] = json!(cells as f64 / list.len() as f64);
    }
    for (kind, (range, _)) in w.rays.iter().enumerate() {
        v[format!("rays_{range}m_per_s")] = json!(throughput(t, w, Op::Rays(kind)).await?);
    }
    v["rays_per_call"] = json!(w.rays[0].1[0].len());
    Ok(v)
}

pub fn run(a: QueryBenchArgs) -> Result<()> {
    let v = run_bench(&a)?;
    if a.json {
        println!("{v}");
    } else {
        print_summary(&v);
    }
    Ok(())
}

/// Builds the map, measures in-process, then starts a server on it and measures each transport.
pub fn run_bench(a: &QueryBenchArgs) -> Result<Value> {
    ensure!(a.scans > 0 && a.batch > 0 && a.latency_samples > 0 && a.rays > 0, "counts must be > 0");
    let sim = outdoor_scans(a.scans);
    let t0 = Instant::now();
    let map = build_map(&sim, outdoor_params(), a.build_threads.max(1));
    let build_s = t0.elapsed().as_secs_f64();
    ensure!(map.block_count() > 0, "the simulated drive produced an empty map");
    let poses: Vec<[f64; 3]> = sim.iter().map(|s| s.origin).collect();
    let w = Workload::new(&map, &poses, a.batch, a.latency_samples, a.rays);
    let dir = TempDir::new()?;
    let mut v = json!({"bench": "query", "scans": sim.len(), "blocks": map.block_count(),
                       "cells_with_evidence": map.cells_with_evidence(), "map_build_s": build_s,
                       "raw_points": sim.iter().map(|s| s.points_world.len()).sum::<usize>()});
    let config = ServerConfig {
        zenoh: ZenohConfig { enabled: true, listen: vec!["tcp/127.0.0.1:0".into()], ..Default::default() },
        ..loopback_server(dir.0.clone())
    };
    runtime()?.block_on(async {
        let mut in_process = InProcess::new(&map);
        v["in_process"] = measure(&mut in_process, &w).await?;
        in_process.visit = true;
        v["in_process"]["points_visited_per_s"] = json!(throughput(&mut in_process, &w, Op::Points).await?);
        if a.in_process_only {
            return Ok(());
        }
        // Written only now, so no file write precedes the in-process figures; the server
        // loads its own copy, so this one goes.
        crate::store::save_map(&dir.0.join(format!("{MAP}.bgkmap")), &map)?;
        drop(map);
        let running = start(&config).await?;
        let locator = running.zenoh_locators.first().cloned().unwrap_or_default();
        let r = measure_all(running.grpc_addr, running.http_addr, &locator, &w, &sim, &mut v).await;
        running.shutdown().await?;
        r
    })?;
    Ok(v)
}

/// Every network transport, then gRPC single-point latency while ingesting.
async fn measure_all(
    grpc: SocketAddr,
    http: SocketAddr,
    zenoh_locator: &str,
    w: &Workload,
    sim: &[SimScan],
    v: &mut Value,
) -> Result<()> {
    v["grpc"] = measure(&mut Grpc::connect(grpc, w).await?, w).await?;
    v["http"] = measure(&mut Http::connect(http, w).await?, w).await?;
    let mut zenoh = Zenoh::connect(zenoh_locator, w).await?;
    let z = measure(&mut zenoh, w).await;
    zenoh.close().await;
    v["zenoh"] = z?;
    // The drive's dense scans, then scans a 10 Hz sensor of the room's size sends (a dense scan
    // takes longer than 100 ms to integrate, so the first stream cannot reach 10 scans/s).
    let (_, room) = crate::sim::simulate(1, 24, &crate::sim::Lidar::default());
    for ((tag, source), scans) in UNDER_INGEST.into_iter().zip([sim, &room]) {
        let (p50, p99, n, rate) = latencies_under_ingest(grpc, w, scans, source).await?;
        let g = &mut v["grpc"];
        g[format!("single_p50_us_under_{tag}ingest")] = json!(p50);
        g[format!("single_p99_us_under_{tag}ingest")] = json!(p99);
        g[format!("{tag}background_scans")] = json!(n);
        g[format!("{tag}background_scans_per_s")] = json!(rate);
        g[format!("{tag}background_points_per_scan")] =
            json!(scans.iter().map(|s| s.points_world.len()).sum::<usize>() / scans.len().max(1));
    }
    Ok(())
}

/// The background streams of the latency-under-ingest runs (the drive's dense scans, then
/// room-sized scans): the prefix of their JSON keys and the scan source they insert as.
const UNDER_INGEST: [(&str, &str); 2] = [("", "bench-background"), ("room_", "bench-background-room")];

fn print_summary(v: &Value) {
    let f = |p: &str| v.pointer(p).and_then(Value::as_f64).unwrap_or(f64::NAN);
    println!(
        "query bench: map of {} scans of the simulated 64-beam drive, {} blocks, {} cells with evidence",
        v["scans"], v["blocks"], v["cells_with_evidence"]
    );
    for t in ["in_process", "grpc", "http", "zenoh"].into_iter().filter(|t| !v[*t].is_null()) {
        println!(
            "  {t}: points ({} per call) {:.2} M/s{}; single point p50 {:.0} µs p99 {:.0} µs; boxes 1 m {:.3} ms, \
             10 m {:.2} ms ({:.0} cells); rays ({} per call) 8 m {:.3} M/s, 30 m {:.3} M/s",
            v[t]["batch"],
            f(&format!("/{t}/points_per_s")) / 1e6,
            match v[t]["points_visited_per_s"].as_f64() {
                Some(r) => format!(" into a vector, {:.2} M/s visited", r / 1e6),
                None => String::new(),
            },
            f(&format!("/{t}/single_p50_us")),
            f(&format!("/{t}/single_p99_us")),
            f(&format!("/{t}/box_1m_ms_median")),
            f(&format!("/{t}/box_10m_ms_median")),
            f(&format!("/{t}/box_10m_cells_mean")),
            v[t]["rays_per_call"],
            f(&format!("/{t}/rays_8m_per_s")) / 1e6,
            f(&format!("/{t}/rays_30m_per_s")) / 1e6,
        );
    }
    if v["grpc"].is_null() {
        return;
    }
    for (tag, _) in UNDER_INGEST {
        println!(
            "  gRPC single point while ingesting {} scans of {} points at {:.1} scans/s: p50 {:.0} µs, p99 {:.0} µs",
            v["grpc"][format!("{tag}background_scans")],
            v["grpc"][format!("{tag}background_points_per_scan")],
            f(&format!("/grpc/{tag}background_scans_per_s")),
            f(&format!("/grpc/single_p50_us_under_{tag}ingest")),
            f(&format!("/grpc/single_p99_us_under_{tag}ingest"))
        );
    }
}
