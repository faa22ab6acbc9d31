//! The transports of `bgkmap bench query` and the [`QueryTransport`] trait they share:
//! in-process (the reference), gRPC, HTTP JSON and zenoh, each with its requests encoded once up
//! front so a run times the server, not the client's encoding; and gRPC single-point latency
//! while scans are being ingested.

use super::common::percentile;
use super::server::{Client, HttpConnection, connect, xyz_f32};
use super::world::Workload;
use crate::api::pb;
use crate::core::query::{BoxQuery, StopAt, cast_ray, for_each_point, query_box, query_points};
use crate::core::{EvidenceMap, Thresholds};
use crate::sim::SimScan;
use anyhow::{Context, Result, ensure};
use serde_json::json;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

pub(super) const MAP: &str = "bench";

/// A query transport under test. Every call answers how many items (points, cells, rays) the
/// answer held, so a run can check it got a full answer.
pub(super) trait QueryTransport {
    fn name(&self) -> &'static str;
    /// Batch `i` of [`Workload::point_batches`].
    async fn points(&mut self, w: &Workload, i: usize) -> Result<usize>;
    /// Single point `i` of [`Workload::singles`].
    async fn single(&mut self, w: &Workload, i: usize) -> Result<usize>;
    /// Box `i` of edge kind `kind` of [`Workload::boxes`].
    async fn boxed(&mut self, w: &Workload, kind: usize, i: usize) -> Result<usize>;
    /// Ray batch `i` of length kind `kind` of [`Workload::rays`].
    async fn rays(&mut self, w: &Workload, kind: usize, i: usize) -> Result<usize>;
}

/// Largest box answer accepted in-process (the server's default limit).
const MAX_BOX_CELLS: u64 = 4_000_000;

/// The core's query functions on the map itself (no service, no copies).
#[derive(Debug)]
pub(super) struct InProcess<'m> {
    map: &'m EvidenceMap,
    th: Thresholds,
    batches: Vec<Vec<[f64; 3]>>,
    /// Batched points go through [`for_each_point`], every answer read where it is made (as
    /// the gRPC service writes its columns), instead of [`query_points`]' vector of answers.
    pub(super) visit: bool,
}

impl<'m> InProcess<'m> {
    pub(super) fn new(map: &'m EvidenceMap) -> Self {
        Self { map, th: map.params().thresholds, batches: Vec::new(), visit: false }
    }

    fn widen(p: &[f32; 3]) -> [f64; 3] {
        p.map(f64::from)
    }
}

impl QueryTransport for InProcess<'_> {
    fn name(&self) -> &'static str {
        "in_process"
    }

    async fn points(&mut self, w: &Workload, i: usize) -> Result<usize> {
        if self.batches.is_empty() {
            self.batches = w.point_batches.iter().map(|b| b.iter().map(Self::widen).collect()).collect();
        }
        let points = &self.batches[i];
        if !self.visit {
            return Ok(std::hint::black_box(query_points(self.map, points, &self.th)).len());
        }
        // Every field of every answer goes into the sum, so none of it can be left uncomputed.
        let (mut n, mut sum) = (0, 0.0);
        for_each_point(self.map, points, &self.th, |a| {
            n += 1;
            if let Some(a) = a {
                let e = a.estimate;
                let key = a.cell.x ^ a.cell.y ^ a.cell.z ^ e.state as i32;
                sum += e.probability + e.variance + (e.evidence.a ^ e.evidence.b ^ i64::from(key)) as f64;
            }
        });
        std::hint::black_box(sum);
        Ok(n)
    }

    async fn single(&mut self, w: &Workload, i: usize) -> Result<usize> {
        let p = [Self::widen(&w.singles[i])];
        Ok(std::hint::black_box(query_points(self.map, &p, &self.th)).len())
    }

    async fn boxed(&mut self, w: &Workload, kind: usize, i: usize) -> Result<usize> {
        let (min_world, max_world) = w.boxes[kind].1[i];
        let q = BoxQuery { min_world, max_world, state: None, coarsen: 0 };
        Ok(query_box(self.map, &q, &self.th, MAX_BOX_CELLS)?.len())
    }

    async fn rays(&mut self, w: &Workload, kind: usize, i: usize) -> Result<usize> {
        let mut n = 0;
        for r in &w.rays[kind].1[i] {
            std::hint::black_box(cast_ray(
                self.map,
                r.origin,
                r.direction,
                r.max_range_m,
                StopAt::Occupied,
                &self.th,
            )?);
            n += 1;
        }
        Ok(n)
    }
}

/// gRPC (tonic client on one HTTP/2 connection).
#[derive(Debug)]
pub(super) struct Grpc {
    client: Client,
    batches: Vec<Vec<u8>>,
    singles: Vec<Vec<u8>>,
    rays: Vec<Vec<Vec<pb::Ray>>>,
}

fn points_request(xyz: Vec<u8>) -> pb::QueryPointsRequest {
    pb::QueryPointsRequest { map: MAP.into(), xyz_f32: xyz, thresholds: None }
}

fn f32_bytes(points: &[[f32; 3]]) -> Vec<u8> {
    points.iter().flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes())).collect()
}

/// The workload's ray batches as protobuf rays, per length kind.
fn pb_rays(w: &Workload) -> Vec<Vec<Vec<pb::Ray>>> {
    w.rays
        .iter()
        .map(|(_, batches)| {
            batches
                .iter()
                .map(|b| {
                    b.iter()
                        .map(|r| pb::Ray {
                            origin: r.origin.to_vec(),
                            direction: r.direction.to_vec(),
                            max_range: r.max_range_m,
                        })
                        .collect()
                })
                .collect()
        })
        .collect()
}

fn box_request(w: &Workload, kind: usize, i: usize) -> pb::QueryBoxRequest {
    let (min, max) = w.boxes[kind].1[i];
    pb::QueryBoxRequest { map: MAP.into(), min: min.to_vec(), max: max.to_vec(), ..Default::default() }
}

fn rays_request(rays: Vec<pb::Ray>) -> pb::CastRaysRequest {
    pb::CastRaysRequest { map: MAP.into(), rays, stop_at: pb::StopAt::Occupied as i32, thresholds: None }
}

impl Grpc {
    pub(super) async fn connect(addr: SocketAddr, w: &Workload) -> Result<Self> {
        Ok(Self {
            client: connect(addr).await?,
            batches: w.point_batches.iter().map(|b| f32_bytes(b)).collect(),
            singles: w.singles.iter().map(|p| f32_bytes(std::slice::from_ref(p))).collect(),
            rays: pb_rays(w),
        })
    }
}

impl QueryTransport for Grpc {
    fn name(&self) -> &'static str {
        "grpc"
    }

    async fn points(&mut self, _: &Workload, i: usize) -> Result<usize> {
        let req = points_request(self.batches[i].clone());
        Ok(self.client.query_points(req).await.context("QueryPoints")?.get_ref().probability.len())
    }

    async fn single(&mut self, _: &Workload, i: usize) -> Result<usize> {
        let req = points_request(self.singles[i].clone());
        Ok(self.client.query_points(req).await.context("QueryPoints")?.get_ref().probability.len())
    }

    async fn boxed(&mut self, w: &Workload, kind: usize, i: usize) -> Result<usize> {
        let req = box_request(w, kind, i);
        Ok(self.client.query_box(req).await.context("QueryBox")?.get_ref().probability.len())
    }

    async fn rays(&mut self, _: &Workload, kind: usize, i: usize) -> Result<usize> {
        let req = rays_request(self.rays[kind][i].clone());
        Ok(self.client.cast_rays(req).await.context("CastRays")?.get_ref().results.len())
    }
}

fn zbytes(m: impl prost::Message) -> zenoh::bytes::ZBytes {
    zenoh::bytes::ZBytes::from(m.encode_to_vec())
}

/// zenoh queries (`bgkmap/<map>/query/{points,box,rays}`) from a peer of the bench's own, with
/// the gRPC requests' protobuf payloads, encoded up front.
pub(super) struct Zenoh {
    session: zenoh::Session,
    points: zenoh::query::Querier<'static>,
    boxes: zenoh::query::Querier<'static>,
    rays: zenoh::query::Querier<'static>,
    point_payloads: Vec<zenoh::bytes::ZBytes>,
    single_payloads: Vec<zenoh::bytes::ZBytes>,
    box_payloads: Vec<Vec<zenoh::bytes::ZBytes>>,
    ray_payloads: Vec<Vec<zenoh::bytes::ZBytes>>,
}

impl Zenoh {
    /// A peer connected to the server's zenoh `locator`.
    pub(super) async fn connect(locator: &str, w: &Workload) -> Result<Self> {
        let session = super::zenoh::peer(locator)?;
        let querier = async |what: &str| {
            let key = format!("bgkmap/{MAP}/query/{what}");
            session
                .declare_querier(key.clone())
                .timeout(Duration::from_secs(60))
                .await
                .map_err(|e| anyhow::anyhow!("declaring a querier on {key}: {e}"))
        };
        let (points, boxes, rays) = (querier("points").await?, querier("box").await?, querier("rays").await?);
        let single = |p: &[f32; 3]| zbytes(points_request(f32_bytes(std::slice::from_ref(p))));
        Ok(Self {
            point_payloads: w.point_batches.iter().map(|b| zbytes(points_request(f32_bytes(b)))).collect(),
            single_payloads: w.singles.iter().map(single).collect(),
            box_payloads: (0..w.boxes.len())
                .map(|k| (0..w.boxes[k].1.len()).map(|i| zbytes(box_request(w, k, i))).collect())
                .collect(),
            ray_payloads: pb_rays(w)
                .into_iter()
                .map(|kind| kind.into_iter().map(|r| zbytes(rays_request(r))).collect())
                .collect(),
            session,
            points,
            boxes,
            rays,
        })
    }

    /// One query's decoded answer (a server error is this call's error).
    async fn ask<M: prost::Message + Default + 'static>(
        querier: &zenoh::query::Querier<'static>,
        payload: &zenoh::bytes::ZBytes,
    ) -> Result<M> {
        let key = querier.key_expr().to_string();
        let replies =
            querier.get().payload(payload.clone()).await.map_err(|e| anyhow::anyhow!("get {key}: {e}"))?;
        let reply = replies.recv_async().await.map_err(|_| anyhow::anyhow!("no reply on {key}"))?;
        match reply.result() {
            Ok(sample) => Ok(crate::api::codec::decode::<M>(&sample.payload().to_bytes())?),
            Err(e) => anyhow::bail!("{key}: {}", e.payload().try_to_string().unwrap_or_default()),
        }
    }

    pub(super) async fn close(self) {
        let _ = self.session.close().await;
    }
}

impl QueryTransport for Zenoh {
    fn name(&self) -> &'static str {
        "zenoh"
    }

    async fn points(&mut self, _: &Workload, i: usize) -> Result<usize> {
        let a: pb::QueryPointsResponse = Self::ask(&self.points, &self.point_payloads[i]).await?;
        Ok(a.probability.len())
    }

    async fn single(&mut self, _: &Workload, i: usize) -> Result<usize> {
        let a: pb::QueryPointsResponse = Self::ask(&self.points, &self.single_payloads[i]).await?;
        Ok(a.probability.len())
    }

    async fn boxed(&mut self, _: &Workload, kind: usize, i: usize) -> Result<usize> {
        let a: pb::QueryBoxResponse = Self::ask(&self.boxes, &self.box_payloads[kind][i]).await?;
        Ok(a.probability.len())
    }

    async fn rays(&mut self, _: &Workload, kind: usize, i: usize) -> Result<usize> {
        let a: pb::CastRaysResponse = Self::ask(&self.rays, &self.ray_payloads[kind][i]).await?;
        Ok(a.results.len())
    }
}

/// HTTP JSON over one keep-alive connection. Answers are counted by their JSON objects (one
/// per point, cell or ray, besides the envelope) rather than parsed, so parsing on the client
/// does not count against the server.
#[derive(Debug)]
pub(super) struct Http {
    conn: HttpConnection,
    batches: Vec<Vec<u8>>,
    singles: Vec<Vec<u8>>,
    boxes: Vec<Vec<Vec<u8>>>,
    rays: Vec<Vec<Vec<u8>>>,
}

fn objects(body: &[u8]) -> usize {
    body.iter().filter(|&&b| b == b'{').count()
}

impl Http {
    pub(super) async fn connect(addr: SocketAddr, w: &Workload) -> Result<Self> {
        let points = |b: &[[f32; 3]]| json!({ "points": b }).to_string().into_bytes();
        let boxes = w
            .boxes
            .iter()
            .map(|(_, list)| {
                list.iter().map(|(lo, hi)| json!({"min": lo, "max": hi}).to_string().into_bytes()).collect()
            })
            .collect();
        let rays = w
            .rays
            .iter()
            .map(|(_, batches)| {
                batches
                    .iter()
                    .map(|b| {
                        let list: Vec<_> = b
                            .iter()
                            .map(|r| json!({"origin": r.origin, "direction": r.direction, "max_range": r.max_range_m}))
                            .collect();
                        json!({"rays": list, "stop_at": "occupied"}).to_string().into_bytes()
                    })
                    .collect()
            })
            .collect();
        Ok(Self {
            conn: HttpConnection::connect(addr).await?,
            batches: w.point_batches.iter().map(|b| points(b)).collect(),
            singles: w.singles.iter().map(|p| points(std::slice::from_ref(p))).collect(),
            boxes,
            rays,
        })
    }

    async fn post(&mut self, what: &str, body: &[u8], envelope: usize) -> Result<usize> {
        let path = format!("/v1/maps/{MAP}/query/{what}");
        Ok(objects(&self.conn.post_json(&path, body).await?).saturating_sub(envelope))
    }
}

impl QueryTransport for Http {
    fn name(&self) -> &'static str {
        "http"
    }

    async fn points(&mut self, _: &Workload, i: usize) -> Result<usize> {
        let body = std::mem::take(&mut self.batches[i]);
        let n = self.post("points", &body, 1).await;
        self.batches[i] = body;
        n
    }

    async fn single(&mut self, _: &Workload, i: usize) -> Result<usize> {
        let body = std::mem::take(&mut self.singles[i]);
        let n = self.post("points", &body, 1).await;
        self.singles[i] = body;
        n
    }

    async fn boxed(&mut self, _: &Workload, kind: usize, i: usize) -> Result<usize> {
        let body = std::mem::take(&mut self.boxes[kind][i]);
        // Envelope: the answer and its `counts`.
        let n = self.post("box", &body, 2).await;
        self.boxes[kind][i] = body;
        n
    }

    async fn rays(&mut self, _: &Workload, kind: usize, i: usize) -> Result<usize> {
        let body = std::mem::take(&mut self.rays[kind][i]);
        let n = self.post("rays", &body, 1).await;
        self.rays[kind][i] = body;
        n
    }
}

/// Background ingest: at most one scan per this period.
const BACKGROUND_PERIOD: Duration = Duration::from_millis(100);
/// A latency run under ingest lasts at least this long (and the workload's sample count).
const UNDER_INGEST_MIN: Duration = Duration::from_secs(4);

/// gRPC single-point latencies while another connection inserts `sim`'s scans (as `source`,
/// each acknowledged once applied) at up to 10 per second:
/// (p50 µs, p99 µs, scans applied, scans applied per second).
pub(super) async fn latencies_under_ingest(
    grpc: SocketAddr,
    w: &Workload,
    sim: &[SimScan],
    source: &str,
) -> Result<(f64, f64, u64, f64)> {
    let scans: Vec<pb::Scan> =
        sim.iter().map(|s| pb::Scan::world(source, 0, s.origin, &s.points_world)).collect();
    let mut writer = connect(grpc).await?;
    let (stop, mut stopped) = tokio::sync::watch::channel(false);
    let background = tokio::spawn(async move {
        let mut tick = tokio::time::interval(BACKGROUND_PERIOD);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let (mut applied, t0) = (0u64, Instant::now());
        for (seq, scan) in (1u64..).zip(scans.iter().cycle()) {
            tokio::select! {
                biased;
                _ = stopped.changed() => break,
                _ = tick.tick() => {}
            }
            let scan = pb::Scan { seq, ..scan.clone() };
            let req = pb::InsertScanRequest { map: MAP.into(), scan: Some(scan), wait_applied: true };
            if writer.insert_scan(req).await.context("background InsertScan")?.get_ref().applied {
                applied += 1;
            }
        }
        anyhow::Ok((applied, t0.elapsed().as_secs_f64()))
    });
    let mut client = connect(grpc).await?;
    let mut us = Vec::new();
    let t0 = Instant::now();
    let mut i = 0;
    while us.len() < w.singles.len() || t0.elapsed() < UNDER_INGEST_MIN {
        let req = points_request(xyz_f32(&[w.singles[i % w.singles.len()].map(f64::from)]));
        let t = Instant::now();
        let answer = client.query_points(req).await.context("QueryPoints")?;
        us.push(t.elapsed().as_secs_f64() * 1e6);
        ensure!(answer.get_ref().probability.len() == 1, "QueryPoints answered the wrong number of points");
        i += 1;
    }
    let _ = stop.send(true);
    let (applied, secs) = background.await.context("background ingest task")??;
    Ok((percentile(&mut us, 0.5), percentile(&mut us, 0.99), applied, applied as f64 / secs))
}
