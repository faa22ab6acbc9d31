//! HTTP JSON transport (axum), mirroring the gRPC calls under `/v1/…`, plus `/healthz`,
//! `/readyz` and `/metrics` (Prometheus text). The web viewer, its binary cells endpoint and
//! the change stream (SSE) are merged in from [`super::viewer`] and [`super::watch`].
//!
//! Handlers parse the body themselves so a bad request gets a 400 whose message names the field
//! (serde's "missing field `seq`", or ours), convert, call one service method, convert back.

use super::status::http_code;
use crate::core::query::{BoxError, BoxQuery, RayError, RayHit, StopAt, cast_ray, query_box, query_points};
use crate::core::{CellState, MapParams, PointFrame, Pose, RangeMode, Thresholds};
use crate::io::pcd::read_pcd;
use crate::service::{MapInfo, MapService, ScanInput, ServiceError};
use axum::Router;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Deserialize;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

/// HTTP limits.
#[derive(Debug, Clone)]
pub struct HttpConfig {
    /// Largest box query, in lattice positions. Default 4 M.
    pub max_box_cells: u64,
    /// Largest request body. Default 64 MiB.
    pub max_body_bytes: usize,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self { max_box_cells: 4_000_000, max_body_bytes: 64 << 20 }
    }
}

#[derive(Debug, Default)]
struct Counters {
    queries: [AtomicU64; 3],
    query_micros: [AtomicU64; 3],
}

#[derive(Clone)]
pub(super) struct AppState {
    pub(super) service: Arc<MapService>,
    config: HttpConfig,
    counters: Arc<Counters>,
}

/// An error answer: status code and a JSON body `{"error": message}`.
#[derive(Debug)]
pub struct ApiError(StatusCode, String);

impl ApiError {
    pub(super) fn bad(msg: impl Into<String>) -> Self {
        Self(StatusCode::BAD_REQUEST, msg.into())
    }

    pub(super) fn gone(msg: impl Into<String>) -> Self {
        Self(StatusCode::GONE, msg.into())
    }

    pub(super) fn internal(msg: impl Into<String>) -> Self {
        Self(StatusCode::INTERNAL_SERVER_ERROR, msg.into())
    }
}

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        Self(StatusCode::from_u16(http_code(&e)).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR), e.to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut r = (self.0, axum::Json(json!({ "error": self.1 }))).into_response();
        if self.0 == StatusCode::TOO_MANY_REQUESTS {
            r.headers_mut().insert(header::RETRY_AFTER, header::HeaderValue::from_static("1"));
        }
        r
    }
}

pub(super) type ApiResult = Result<Response, ApiError>;

/// `/readyz`: 200 `ready`, or 503 `degraded` with one line per map that refuses ingest (queries
/// still work; `/healthz` stays 200).
async fn readyz(State(st): State<AppState>) -> Response {
    let degraded = st.service.degraded();
    if degraded.is_empty() {
        return "ready\n".into_response();
    }
    let mut body = String::from("degraded\n");
    for (map, reason) in degraded {
        body.push_str(&format!("map {map}: read-only: {reason}\n"));
    }
    (StatusCode::SERVICE_UNAVAILABLE, body).into_response()
}

/// The HTTP router.
pub fn router(service: Arc<MapService>, config: HttpConfig) -> Router {
    let limit = config.max_body_bytes;
    let viewer = super::viewer::routes(service.clone(), config.max_box_cells);
    let state = AppState { service, config, counters: Arc::default() };
    Router::new()
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/maps", get(list_maps))
        .route("/v1/maps/{map}", get(get_map).put(create_map))
        .route("/v1/maps/{map}/scans", post(insert_scan))
        .route("/v1/maps/{map}/query/points", post(points_query))
        .route("/v1/maps/{map}/query/box", post(box_query))
        .route("/v1/maps/{map}/query/rays", post(rays_query))
        .route("/v1/maps/{map}/merge", post(super::http_ops::merge))
        .route("/v1/maps/{map}/retract", post(super::http_ops::retract))
        .route("/v1/maps/{map}/repose", post(super::http_ops::repose))
        .layer(DefaultBodyLimit::max(limit))
        .with_state(state)
        .merge(viewer)
}

pub(super) fn parse<T: serde::de::DeserializeOwned>(body: &Bytes) -> Result<T, ApiError> {
    serde_json::from_slice(body).map_err(|e| ApiError::bad(format!("invalid JSON body: {e}")))
}

fn info_json(i: &MapInfo) -> Value {
    let sources: serde_json::Map<String, Value> = i
        .sources
        .iter()
        .map(|(k, s)| {
            let v = json!({"received": s.received, "applied": s.applied, "duplicates": s.duplicates,
                           "rejected": s.rejected, "highest_seq": s.highest_seq, "pending": s.pending,
                           "gaps": s.gaps, "pruned": s.pruned, "retracted": s.retracted,
                           "dropped_points": s.dropped_points});
            (k.clone(), v)
        })
        .collect();
    let params: serde_json::Map<String, Value> = i
        .params
        .to_pairs()
        .into_iter()
        .map(|(k, v)| {
            // `sub_cells` is a whole number, as the `PUT` body takes it; the others are numbers or
            // flags (or names).
            let value = if k == "sub_cells" {
                v.parse::<u64>().ok().map(Value::from)
            } else {
                v.parse::<f64>().map(Value::from).or_else(|_| v.parse::<bool>().map(Value::from)).ok()
            };
            (k.to_string(), value.unwrap_or(Value::String(v)))
        })
        .collect();
    json!({"map": i.name, "params": params, "version": i.version, "scans": i.scans, "blocks": i.blocks,
           "cells_with_evidence": i.cells_with_evidence, "queued": i.queued, "sources": sources,
           "journal_bytes": i.journal_bytes, "corrupt_blocks": i.corrupt_blocks, "read_only": i.read_only})
}

async fn list_maps(State(st): State<AppState>) -> ApiResult {
    let maps: Vec<Value> = st.service.list_maps().iter().map(info_json).collect();
    Ok(axum::Json(json!({ "maps": maps })).into_response())
}

async fn get_map(State(st): State<AppState>, Path(map): Path<String>) -> ApiResult {
    Ok(axum::Json(info_json(&st.service.map_info(&map)?)).into_response())
}

/// `PUT /v1/maps/{map}` body: parameters named like the `build` flags; all optional.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ParamsJson {
    resolution: Option<f64>,
    sf2: Option<f64>,
    ell: Option<f64>,
    free_resolution: Option<f64>,
    ds_resolution: Option<f64>,
    max_range: Option<f64>,
    range_mode: Option<String>,
    prior_a: Option<f64>,
    prior_b: Option<f64>,
    p_free: Option<f64>,
    p_occ: Option<f64>,
    var_max: Option<f64>,
    sub_cells: Option<u32>,
}

impl ParamsJson {
    fn to_params(&self) -> Result<MapParams, ApiError> {
        let d = MapParams::default();
        let range_mode = match &self.range_mode {
            None => d.range_mode,
            Some(s) => s.parse::<RangeMode>().map_err(|e| ApiError::bad(e.to_string()))?,
        };
        Ok(MapParams {
            resolution_m: self.resolution.unwrap_or(d.resolution_m),
            sf2: self.sf2.unwrap_or(d.sf2),
            ell_m: self.ell.unwrap_or(d.ell_m),
            free_resolution_m: self.free_resolution.unwrap_or(d.free_resolution_m),
            ds_resolution_m: self.ds_resolution.unwrap_or(d.ds_resolution_m),
            max_range_m: self.max_range.unwrap_or(d.max_range_m),
            range_mode,
            prior_a: self.prior_a.unwrap_or(d.prior_a),
            prior_b: self.prior_b.unwrap_or(d.prior_b),
            origin_as_free: d.origin_as_free,
            sub_cells: self.sub_cells.unwrap_or(d.sub_cells),
            thresholds: Thresholds {
                p_free: self.p_free.unwrap_or(d.thresholds.p_free),
                p_occ: self.p_occ.unwrap_or(d.thresholds.p_occ),
                var_max: self.var_max.unwrap_or(d.thresholds.var_max),
            },
        })
    }
}

async fn create_map(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let p: ParamsJson =
        if body.iter().all(u8::is_ascii_whitespace) { ParamsJson::default() } else { parse(&body)? };
    let info = st.service.create_map(&map, p.to_params()?)?;
    Ok((StatusCode::CREATED, axum::Json(info_json(&info))).into_response())
}

/// A sensor pose in JSON (`rotation` as w, x, y, z), for scans and re-poses.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PoseJson {
    translation: [f64; 3],
    rotation: [f64; 4],
}

impl From<PoseJson> for Pose {
    fn from(p: PoseJson) -> Self {
        Pose { translation_m: p.translation, rotation_wxyz: p.rotation }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScanJson {
    source: String,
    seq: u64,
    pose: PoseJson,
    #[serde(default)]
    frame: Option<String>,
    points: Vec<[f32; 3]>,
    #[serde(default)]
    max_range: Option<f64>,
    #[serde(default)]
    stamp_nanos: Option<i64>,
}

fn parse_frame(s: Option<&str>) -> Result<PointFrame, ApiError> {
    match s.unwrap_or("world") {
        "world" => Ok(PointFrame::World),
        "sensor" => Ok(PointFrame::Sensor),
        other => Err(ApiError::bad(format!("invalid frame: {other:?} (world|sensor)"))),
    }
}

async fn insert_scan(
    State(st): State<AppState>,
    Path(map): Path<String>,
    Query(q): Query<HashMap<String, String>>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult {
    let is_pcd = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/x-pcd"));
    let scan = if is_pcd { scan_from_pcd_body(&q, &body)? } else { scan_from_json(&body)? };
    let wait_applied = match q.get("wait_applied").map(String::as_str) {
        None | Some("false" | "0") => false,
        Some("true" | "1" | "") => true,
        Some(other) => {
            return Err(ApiError::bad(format!("query parameter wait_applied: {other:?} is not true|false")));
        }
    };
    let (tx, rx) = tokio::sync::oneshot::channel();
    let options = crate::service::SubmitOptions { wait_applied };
    st.service.submit(&map, scan, options, Box::new(move |r| drop(tx.send(r))))?;
    let ack = rx.await.map_err(|_| ServiceError::ShuttingDown)??;
    Ok(axum::Json(
        json!({"applied": ack.applied, "version": ack.version, "dropped_points": ack.dropped_points}),
    )
    .into_response())
}

fn scan_from_json(body: &Bytes) -> Result<ScanInput, ApiError> {
    let s: ScanJson = parse(body)?;
    Ok(ScanInput {
        frame: parse_frame(s.frame.as_deref())?,
        source: s.source,
        seq: s.seq,
        world_from_sensor: s.pose.into(),
        points: s.points,
        max_range_m: s.max_range,
        stamp_nanos: s.stamp_nanos,
    })
}

/// A raw PCD body: `?source=…&seq=…[&max_range=…][&frame=world|sensor]`; the pose is the
/// file's VIEWPOINT.
fn scan_from_pcd_body(q: &HashMap<String, String>, body: &Bytes) -> Result<ScanInput, ApiError> {
    let source =
        q.get("source").cloned().ok_or_else(|| ApiError::bad("query parameter source is required"))?;
    let seq = q
        .get("seq")
        .ok_or_else(|| ApiError::bad("query parameter seq is required"))?
        .parse::<u64>()
        .map_err(|_| ApiError::bad("query parameter seq must be an unsigned integer"))?;
    let max_range = match q.get("max_range") {
        None => None,
        Some(v) => {
            Some(v.parse::<f64>().map_err(|_| ApiError::bad("query parameter max_range must be a number"))?)
        }
    };
    let stamp_nanos = match q.get("stamp_nanos") {
        None => None,
        Some(v) => Some(
            v.parse::<i64>().map_err(|_| ApiError::bad("query parameter stamp_nanos must be an integer"))?,
        ),
    };
    let cloud = read_pcd(body).map_err(|e| ApiError::bad(e.to_string()))?;
    let vp =
        cloud.viewpoint.ok_or_else(|| ApiError::bad("the PCD has no VIEWPOINT line (the sensor pose)"))?;
    Ok(ScanInput {
        source,
        seq,
        world_from_sensor: Pose {
            translation_m: [vp[0], vp[1], vp[2]],
            rotation_wxyz: [vp[3], vp[4], vp[5], vp[6]],
        },
        frame: parse_frame(q.get("frame").map(String::as_str))?,
        points: cloud.points,
        max_range_m: max_range,
        stamp_nanos,
    })
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ThresholdsJson {
    p_free: Option<f64>,
    p_occ: Option<f64>,
    var_max: Option<f64>,
}

impl ThresholdsJson {
    fn resolve(t: &Option<ThresholdsJson>, d: Thresholds) -> Result<Thresholds, ApiError> {
        let t = t.as_ref();
        let th = Thresholds {
            p_free: t.and_then(|t| t.p_free).unwrap_or(d.p_free),
            p_occ: t.and_then(|t| t.p_occ).unwrap_or(d.p_occ),
            var_max: t.and_then(|t| t.var_max).unwrap_or(d.var_max),
        };
        th.validate().map_err(|e| ApiError::bad(format!("thresholds.{}: {}", e.name, e.reason)))?;
        Ok(th)
    }
}

fn state_str(s: CellState) -> &'static str {
    s.as_str()
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PointsJson {
    points: Vec<[f64; 3]>,
    thresholds: Option<ThresholdsJson>,
}

async fn points_query(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let t0 = std::time::Instant::now();
    let q: PointsJson = parse(&body)?;
    let snap = st.service.snapshot(&map)?;
    let th = ThresholdsJson::resolve(&q.thresholds, snap.map.params().thresholds)?;
    if let Some(i) = q.points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(ApiError::bad(format!("points[{i}]: coordinates must be finite")));
    }
    snap.check_points(&q.points)?;
    let answers = query_points(&snap.map, &q.points, &th);
    let mut results = Vec::with_capacity(answers.len());
    for (i, a) in answers.iter().enumerate() {
        let a = a.ok_or_else(|| ApiError::bad(format!("points[{i}]: outside the map's key range")))?;
        let e = a.estimate;
        results.push(json!({"probability": e.probability, "variance": e.variance,
            "state": state_str(e.state), "cell": [a.cell.x, a.cell.y, a.cell.z]}));
    }
    st.count(0, t0);
    Ok(axum::Json(json!({"results": results, "version": snap.version})).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BoxJson {
    min: [f64; 3],
    max: [f64; 3],
    state: Option<String>,
    #[serde(default)]
    coarsen: u8,
    #[serde(default)]
    counts_only: bool,
    thresholds: Option<ThresholdsJson>,
}

fn parse_state(s: &str) -> Result<CellState, ApiError> {
    match s {
        "free" => Ok(CellState::Free),
        "occupied" => Ok(CellState::Occupied),
        "unknown" => Ok(CellState::Unknown),
        other => Err(ApiError::bad(format!("state: {other:?} is not free|occupied|unknown"))),
    }
}

async fn box_query(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let t0 = std::time::Instant::now();
    let q: BoxJson = parse(&body)?;
    let snap = st.service.snapshot(&map)?;
    let th = ThresholdsJson::resolve(&q.thresholds, snap.map.params().thresholds)?;
    let state = q.state.as_deref().map(parse_state).transpose()?;
    let bq = BoxQuery { min_world: q.min, max_world: q.max, state, coarsen: q.coarsen };
    snap.check_box(q.min, q.max)?;
    // A box over the limit is a bad request (400, as gRPC's INVALID_ARGUMENT); the message
    // gives the limit.
    let cells = query_box(&snap.map, &bq, &th, st.config.max_box_cells)
        .map_err(|e: BoxError| ApiError::bad(e.to_string()))?;
    let counts = crate::core::query::count_box(&cells);
    let mut out = json!({"counts": {"free": counts[0], "occupied": counts[1], "unknown": counts[2]},
                         "version": snap.version});
    if !q.counts_only {
        let list: Vec<Value> = cells
            .iter()
            .map(|c| {
                json!({"min_cell": [c.min_cell.x, c.min_cell.y, c.min_cell.z], "size_cells": c.size_cells,
                       "probability": c.estimate.probability, "variance": c.estimate.variance,
                       "state": state_str(c.estimate.state)})
            })
            .collect();
        out["cells"] = Value::Array(list);
    }
    st.count(1, t0);
    Ok(axum::Json(out).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RayJson {
    origin: [f64; 3],
    direction: [f64; 3],
    max_range: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RaysJson {
    rays: Vec<RayJson>,
    stop_at: Option<String>,
    thresholds: Option<ThresholdsJson>,
}

async fn rays_query(State(st): State<AppState>, Path(map): Path<String>, body: Bytes) -> ApiResult {
    let t0 = std::time::Instant::now();
    let q: RaysJson = parse(&body)?;
    let snap = st.service.snapshot(&map)?;
    let th = ThresholdsJson::resolve(&q.thresholds, snap.map.params().thresholds)?;
    let stop = match q.stop_at.as_deref().unwrap_or("occupied") {
        "occupied" => StopAt::Occupied,
        "not_free" | "unknown" => StopAt::NotFree,
        other => return Err(ApiError::bad(format!("stop_at: {other:?} is not occupied|not_free"))),
    };
    let mut results = Vec::with_capacity(q.rays.len());
    for (i, r) in q.rays.iter().enumerate() {
        let hit = cast_ray(&snap.map, r.origin, r.direction, r.max_range, stop, &th)
            .map_err(|e: RayError| ApiError::bad(format!("rays[{i}]: {e}")))?;
        let reach = match hit {
            RayHit::Clear => r.max_range,
            RayHit::Blocked { distance_m, .. } => distance_m + snap.map.params().resolution_m * 3f64.sqrt(),
        };
        snap.check_ray(r.origin, r.direction, reach, format_args!("rays[{i}]"))?;
        results.push(match hit {
            RayHit::Clear => json!({"blocked": false, "verdict": "clear"}),
            RayHit::Blocked { cell, distance_m, estimate } => json!({"blocked": true, "verdict": "blocked",
                "cell": [cell.x, cell.y, cell.z], "distance": distance_m,
                "state": state_str(estimate.state), "probability": estimate.probability}),
        });
    }
    st.count(2, t0);
    Ok(axum::Json(json!({"results": results, "version": snap.version})).into_response())
}

impl AppState {
    fn count(&self, kind: usize, t0: std::time::Instant) {
        self.counters.queries[kind].fetch_add(1, Ordering::Relaxed);
        self.counters.query_micros[kind].fetch_add(t0.elapsed().as_micros() as u64, Ordering::Relaxed);
    }
}

async fn metrics(State(st): State<AppState>) -> Response {
    use std::fmt::Write as _;
    let mut out = String::new();
    let maps = st.service.list_maps();
    let _ = writeln!(out, "# TYPE bgkmap_scans_total counter");
    for i in &maps {
        for (src, s) in &i.sources {
            for (what, v) in [
                ("received", s.received),
                ("applied", s.applied),
                ("duplicate", s.duplicates),
                ("rejected", s.rejected),
            ] {
                let _ = writeln!(
                    out,
                    "bgkmap_scans_total{{map=\"{}\",source=\"{}\",outcome=\"{what}\"}} {v}",
                    i.name, src
                );
            }
        }
    }
    let _ = writeln!(out, "# TYPE bgkmap_dropped_points_total counter");
    for i in &maps {
        for (src, s) in &i.sources {
            let (map, n) = (&i.name, s.dropped_points);
            let _ = writeln!(out, "bgkmap_dropped_points_total{{map=\"{map}\",source=\"{src}\"}} {n}");
        }
    }
    let _ = writeln!(out, "# TYPE bgkmap_integration_seconds_total counter");
    for i in &maps {
        let _ = writeln!(
            out,
            "bgkmap_integration_seconds_total{{map=\"{}\"}} {}",
            i.name, i.integration_seconds_total
        );
    }
    let _ = writeln!(out, "# TYPE bgkmap_queue_depth gauge");
    let _ = writeln!(out, "# TYPE bgkmap_map_version gauge");
    let _ = writeln!(out, "# TYPE bgkmap_journal_bytes gauge");
    let _ = writeln!(out, "# TYPE bgkmap_corrupt_blocks gauge");
    let _ = writeln!(out, "# TYPE bgkmap_map_read_only gauge");
    for i in &maps {
        let _ = writeln!(out, "bgkmap_queue_depth{{map=\"{}\"}} {}", i.name, i.queued);
        let _ = writeln!(out, "bgkmap_map_version{{map=\"{}\"}} {}", i.name, i.version);
        let _ = writeln!(out, "bgkmap_journal_bytes{{map=\"{}\"}} {}", i.name, i.journal_bytes);
        let _ = writeln!(out, "bgkmap_corrupt_blocks{{map=\"{}\"}} {}", i.name, i.corrupt_blocks);
        let _ =
            writeln!(out, "bgkmap_map_read_only{{map=\"{}\"}} {}", i.name, u8::from(i.read_only.is_some()));
    }
    let _ = writeln!(out, "# TYPE bgkmap_http_queries_total counter");
    let _ = writeln!(out, "# TYPE bgkmap_http_query_seconds_total counter");
    for (k, name) in ["points", "box", "rays"].iter().enumerate() {
        let n = st.counters.queries[k].load(Ordering::Relaxed);
        let us = st.counters.query_micros[k].load(Ordering::Relaxed);
        let _ = writeln!(out, "bgkmap_http_queries_total{{kind=\"{name}\"}} {n}");
        let _ = writeln!(out, "bgkmap_http_query_seconds_total{{kind=\"{name}\"}} {}", us as f64 / 1e6);
    }
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out).into_response()
}
