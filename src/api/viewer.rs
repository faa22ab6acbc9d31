//! The web viewer's HTTP side: the page and its assets at `/` (embedded in the binary), the
//! binary cells endpoint, one cell's details, recent sensor poses, and the change stream (SSE,
//! see [`super::watch`]).
//!
//! The page's sources live in `src/api/viewer/` (`src/*.js`, bundled with three.js by
//! `src/api/viewer/build.sh` into the checked-in `dist/viewer.bundle.js`), so `cargo build`
//! needs no Node and the page loads nothing from anywhere but this server.
//!
//! # `GET /v1/maps/{map}/cells` (`application/octet-stream`)
//!
//! Query: `min=x,y,z&max=x,y,z` (a box, world metres; default: the whole map), `coarsen=S`
//! (the finest level wanted, 0–10, default 0: cubes of 2^S cells with summed evidence; raised
//! until the box fits the server's box limit), `state=free|occupied|unknown` with
//! `p_free`, `p_occ`, `var_max` (default: every cell with evidence), and `since=N`: only the
//! cells of blocks changed after version N (coarsen at most 3, so cubes never straddle blocks;
//! `410 Gone` when N predates the version the server opened the map at, whose block history it
//! does not keep: the client reloads the whole map).
//!
//! The answer, all little-endian, sections back to back (each 4- or 8-byte aligned):
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | 4 bytes | magic `BGKC` |
//! | 4 | u32 | layout version, 1 |
//! | 8 | u32 | `n`, cells |
//! | 12 | u32 | `m`, blocks listed (only for `since`: every changed block, so a client drops what it held there) |
//! | 16 | u64 | map version of the answer |
//! | 24 | f64 | resolution (m) |
//! | 32 | u32 | coarsen level used |
//! | 36 | u32 | block edge in cells (8) |
//! | 40 | f32 × 3 | lower corner of the map's blocks (m; zeros for an empty map) |
//! | 52 | f32 × 3 | upper corner of the map's blocks (m) |
//! | 64 | f32 × 3n | cube centres (m) |
//! | 64 + 12n | f32 × n | cube edges (m) |
//! | 64 + 16n | f64 × n | probability |
//! | 64 + 24n | f64 × n | variance |
//! | 64 + 32n | i32 × 3m | block keys |
//!
//! Probability and variance are f64, the server's own values, so a client that applies the
//! state rule (`p < p_free ∧ var < var_max` free, `p > p_occ ∧ var < var_max` occupied, else
//! unknown) to them gets exactly the server's states for any thresholds.

use super::http::ApiError;
use super::watch::{WorldBox, parse_box, parse_xyz, pose_json, sse_updates};
use crate::core::key::{BLOCK_EDGE, BLOCK_SHIFT};
use crate::core::query::{BoxCell, BoxError, BoxQuery, query_box, query_points};
use crate::core::{BlockKey, CellKey, CellState, EvidenceMap, Thresholds};
use crate::service::{MapService, Snapshot};
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde_json::json;
use std::collections::HashMap;
use std::sync::Arc;

const INDEX_HTML: &str = include_str!("viewer/index.html");
const VIEWER_CSS: &str = include_str!("viewer/viewer.css");
const VIEWER_JS: &[u8] = include_bytes!("viewer/dist/viewer.bundle.js");

/// Magic and layout version of the cells answer.
pub const CELLS_MAGIC: &[u8; 4] = b"BGKC";
pub const CELLS_LAYOUT_VERSION: u32 = 1;
const HEADER_BYTES: usize = 64;

#[derive(Clone)]
struct ViewerState {
    service: Arc<MapService>,
    max_box_cells: u64,
}

/// The viewer's routes (merged into the HTTP router).
pub fn routes(service: Arc<MapService>, max_box_cells: u64) -> Router {
    let state = ViewerState { service: service.clone(), max_box_cells };
    let pages = Router::new()
        .route("/", get(|| async { asset("text/html; charset=utf-8", INDEX_HTML.as_bytes()) }))
        .route(
            "/static/viewer.css",
            get(|| async { asset("text/css; charset=utf-8", VIEWER_CSS.as_bytes()) }),
        )
        .route(
            "/static/viewer.bundle.js",
            get(|| async { asset("text/javascript; charset=utf-8", VIEWER_JS) }),
        )
        .route("/v1/maps/{map}/cells", get(cells))
        .route("/v1/maps/{map}/cell", get(cell))
        .route("/v1/maps/{map}/poses", get(poses))
        .with_state(state);
    let updates = Router::new().route("/v1/maps/{map}/updates", get(sse_updates)).with_state(service);
    pages.merge(updates)
}

fn asset(content_type: &'static str, body: &'static [u8]) -> Response {
    ([(header::CONTENT_TYPE, content_type), (header::CACHE_CONTROL, "no-cache")], body).into_response()
}

fn thresholds(q: &HashMap<String, String>, d: Thresholds) -> Result<Thresholds, ApiError> {
    let get = |name: &str, default: f64| match q.get(name) {
        None => Ok(default),
        Some(s) => s.parse::<f64>().map_err(|_| ApiError::bad(format!("{name}: {s:?} is not a number"))),
    };
    let th = Thresholds {
        p_free: get("p_free", d.p_free)?,
        p_occ: get("p_occ", d.p_occ)?,
        var_max: get("var_max", d.var_max)?,
    };
    th.validate().map_err(|e| ApiError::bad(format!("{}: {}", e.name, e.reason)))?;
    Ok(th)
}

fn parse_num<T: std::str::FromStr>(q: &HashMap<String, String>, name: &str) -> Result<Option<T>, ApiError> {
    q.get(name)
        .map(|s| s.parse::<T>().map_err(|_| ApiError::bad(format!("{name}: {s:?} is not a valid number"))))
        .transpose()
}

/// A cells request, validated.
struct CellsQuery {
    bbox: Option<WorldBox>,
    coarsen: u8,
    state: Option<CellState>,
    th: Thresholds,
    since: Option<u64>,
}

impl CellsQuery {
    fn parse(q: &HashMap<String, String>, snap: &Snapshot) -> Result<Self, ApiError> {
        let coarsen: u8 = parse_num(q, "coarsen")?.unwrap_or(0);
        if coarsen > 10 {
            return Err(ApiError::bad(format!("coarsen: must be at most 10, got {coarsen}")));
        }
        let state = match q.get("state").map(String::as_str) {
            None => None,
            Some("free") => Some(CellState::Free),
            Some("occupied") => Some(CellState::Occupied),
            Some("unknown") => Some(CellState::Unknown),
            Some(other) => {
                return Err(ApiError::bad(format!("state: {other:?} is not free|occupied|unknown")));
            }
        };
        let since: Option<u64> = parse_num(q, "since")?;
        if let Some(n) = since {
            if n > snap.version {
                return Err(ApiError::bad(format!(
                    "since: {n} is ahead of the map's version {}",
                    snap.version
                )));
            }
            if n < snap.history_from {
                return Err(ApiError::gone(format!(
                    "since: changes before version {} are not known (the map was opened at that version); load the whole map",
                    snap.history_from
                )));
            }
            if u32::from(coarsen) > BLOCK_SHIFT {
                return Err(ApiError::bad(format!("coarsen: at most {BLOCK_SHIFT} with since")));
            }
        }
        let th = thresholds(q, snap.map.params().thresholds)?;
        Ok(Self { bbox: parse_box(q)?, coarsen, state, th, since })
    }
}

/// The world box spanning cells `lo..=hi` (their centres, so flooring gives them back).
fn cell_span_world(lo: CellKey, hi: CellKey, res: f64) -> ([f64; 3], [f64; 3]) {
    (lo.centre(res), hi.centre(res))
}

/// The lowest and highest block keys of the map.
fn block_extent(map: &EvidenceMap) -> Option<(BlockKey, BlockKey)> {
    map.blocks_unsorted().map(|(k, _)| *k).fold(None, |acc, k| {
        let (lo, hi) = acc.unwrap_or((k, k));
        Some((
            BlockKey::new(lo.x.min(k.x), lo.y.min(k.y), lo.z.min(k.z)),
            BlockKey::new(hi.x.max(k.x), hi.y.max(k.y), hi.z.max(k.z)),
        ))
    })
}

/// The answer's cells and the coarsen level used.
fn select_cells(
    snap: &Snapshot,
    cq: &CellsQuery,
    max_cells: u64,
) -> Result<(Vec<BoxCell>, u8, Vec<BlockKey>), ApiError> {
    let res = snap.map.params().resolution_m;
    let bad = |e: BoxError| ApiError::bad(e.to_string());
    if let Some(since) = cq.since {
        let mut blocks: Vec<BlockKey> =
            snap.block_versions.iter().filter(|(_, v)| **v > since).map(|(k, _)| *k).collect();
        blocks.sort_unstable();
        let mut cells = Vec::new();
        for k in &blocks {
            let (mut lo, mut hi) =
                cell_span_world(k.min_cell(), k.cell(crate::core::key::BLOCK_CELLS - 1), res);
            if let Some((bmin, bmax)) = cq.bbox {
                lo = [0, 1, 2].map(|i| lo[i].max(bmin[i]));
                hi = [0, 1, 2].map(|i| hi[i].min(bmax[i]));
                if (0..3).any(|i| lo[i] > hi[i]) {
                    continue;
                }
            }
            let q = BoxQuery { min_world: lo, max_world: hi, state: cq.state, coarsen: cq.coarsen };
            cells.extend(query_box(&snap.map, &q, &cq.th, u64::MAX).map_err(bad)?);
        }
        return Ok((cells, cq.coarsen, blocks));
    }
    let (min_world, max_world) = match (cq.bbox, block_extent(&snap.map)) {
        (Some(b), _) => b,
        (None, Some((lo, hi))) => {
            cell_span_world(lo.min_cell(), hi.cell(crate::core::key::BLOCK_CELLS - 1), res)
        }
        (None, None) => return Ok((Vec::new(), cq.coarsen, Vec::new())),
    };
    let mut coarsen = cq.coarsen;
    loop {
        let q = BoxQuery { min_world, max_world, state: cq.state, coarsen };
        match query_box(&snap.map, &q, &cq.th, max_cells) {
            Ok(cells) => return Ok((cells, coarsen, Vec::new())),
            Err(BoxError::TooLarge { .. }) if coarsen < 10 => coarsen += 1,
            Err(e) => return Err(bad(e)),
        }
    }
}

/// Packs the answer (layout in the module docs).
fn encode_cells(snap: &Snapshot, cells: &[BoxCell], coarsen: u8, blocks: &[BlockKey]) -> Vec<u8> {
    let res = snap.map.params().resolution_m;
    let (n, m) = (cells.len(), blocks.len());
    let mut out = Vec::with_capacity(HEADER_BYTES + 32 * n + 12 * m);
    out.extend_from_slice(CELLS_MAGIC);
    for v in [CELLS_LAYOUT_VERSION, n as u32, m as u32] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&snap.version.to_le_bytes());
    out.extend_from_slice(&res.to_le_bytes());
    out.extend_from_slice(&u32::from(coarsen).to_le_bytes());
    out.extend_from_slice(&BLOCK_EDGE.unsigned_abs().to_le_bytes());
    let edge_m = f64::from(BLOCK_EDGE) * res;
    let (lo, hi) = match block_extent(&snap.map) {
        Some((lo, hi)) => (
            [lo.x, lo.y, lo.z].map(|v| f64::from(v) * edge_m),
            [hi.x, hi.y, hi.z].map(|v| f64::from(v + 1) * edge_m),
        ),
        None => ([0.0; 3], [0.0; 3]),
    };
    for v in lo.iter().chain(hi.iter()) {
        out.extend_from_slice(&(*v as f32).to_le_bytes());
    }
    for c in cells {
        let half = f64::from(c.size_cells) / 2.0;
        let k = c.min_cell;
        for v in [k.x, k.y, k.z] {
            out.extend_from_slice(&(((f64::from(v) + half) * res) as f32).to_le_bytes());
        }
    }
    for c in cells {
        out.extend_from_slice(&((f64::from(c.size_cells) * res) as f32).to_le_bytes());
    }
    for c in cells {
        out.extend_from_slice(&c.estimate.probability.to_le_bytes());
    }
    for c in cells {
        out.extend_from_slice(&c.estimate.variance.to_le_bytes());
    }
    for k in blocks {
        for v in [k.x, k.y, k.z] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

async fn cells(
    State(st): State<ViewerState>,
    Path(map): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, ApiError> {
    let snap = st.service.snapshot(&map)?;
    let cq = CellsQuery::parse(&q, &snap)?;
    let max = st.max_box_cells;
    let body = tokio::task::spawn_blocking(move || {
        let (cells, coarsen, blocks) = select_cells(&snap, &cq, max)?;
        Ok::<_, ApiError>(encode_cells(&snap, &cells, coarsen, &blocks))
    })
    .await
    .map_err(|e| ApiError::internal(format!("cells task failed: {e}")))??;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], body).into_response())
}

/// `GET /v1/maps/{map}/cell?at=x,y,z[&p_free=…&p_occ=…&var_max=…]`: the cell containing a
/// point, with its Beta posterior (α, β) besides probability, variance and state.
async fn cell(
    State(st): State<ViewerState>,
    Path(map): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, ApiError> {
    let snap = st.service.snapshot(&map)?;
    let at = parse_xyz(q.get("at").map(String::as_str).unwrap_or(""), "at")?;
    let params = snap.map.params();
    let th = thresholds(&q, params.thresholds)?;
    let a = query_points(&snap.map, &[at], &th)
        .pop()
        .flatten()
        .ok_or_else(|| ApiError::bad("at: outside the map's key range"))?;
    let e = a.estimate;
    let (alpha, beta) = e.alpha_beta(params);
    let res = params.resolution_m;
    Ok(axum::Json(json!({
        "cell": [a.cell.x, a.cell.y, a.cell.z], "centre": a.cell.centre(res), "size": res,
        "probability": e.probability, "variance": e.variance, "state": e.state.as_str(),
        "alpha": alpha, "beta": beta, "has_evidence": !e.evidence.is_empty(),
        "thresholds": {"p_free": th.p_free, "p_occ": th.p_occ, "var_max": th.var_max},
        "version": snap.version,
    }))
    .into_response())
}

/// `GET /v1/maps/{map}/poses`: the sensor poses of the most recent scans, oldest first.
async fn poses(State(st): State<ViewerState>, Path(map): Path<String>) -> Result<Response, ApiError> {
    let poses: Vec<_> = st.service.recent_poses(&map)?.iter().map(pose_json).collect();
    Ok(axum::Json(json!({ "poses": poses })).into_response())
}
