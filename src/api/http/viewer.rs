//! The web viewer's HTTP side: the page and its assets at `/` (embedded in the binary), the
//! binary cells endpoint, one cell's details and recent sensor poses; it follows the map through
//! the updates stream ([`super::updates`]). The cells and the cell are read through the
//! service's front door ([`crate::service::query`]) like every other query.
//!
//! The page's sources live in `src/api/http/viewer/` (`src/*.js`, bundled with three.js by
//! `src/api/http/viewer/build.sh` into the checked-in `dist/viewer.bundle.js`), so `cargo build`
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

use super::updates::pose_json;
use super::{ApiError, AppState, parse_box, parse_xyz};
use crate::api::offload;
use crate::core::key::BLOCK_EDGE;
use crate::core::query::BoxCell;
use crate::core::{BlockKey, CellState};
use crate::service::QueryError;
use crate::service::query::ThresholdsIn;
use crate::service::query::cells::{CellsAnswer, CellsError, CellsRequest};
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use serde_json::json;
use std::collections::HashMap;

const INDEX_HTML: &str = include_str!("viewer/index.html");
const VIEWER_CSS: &str = include_str!("viewer/viewer.css");
const VIEWER_JS: &[u8] = include_bytes!("viewer/dist/viewer.bundle.js");

/// Magic and layout version of the cells answer.
pub const CELLS_MAGIC: &[u8; 4] = b"BGKC";
pub const CELLS_LAYOUT_VERSION: u32 = 1;
const HEADER_BYTES: usize = 64;

/// The viewer's routes (merged into the HTTP router).
pub(super) fn routes(state: AppState) -> Router {
    Router::new()
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
        .route("/v1/maps/{map}/updates", get(super::updates::sse_updates))
        .with_state(state)
}

fn asset(content_type: &'static str, body: &'static [u8]) -> Response {
    ([(header::CONTENT_TYPE, content_type), (header::CACHE_CONTROL, "no-cache")], body).into_response()
}

/// A refused viewer query, naming the query-string parameter.
fn refused(e: QueryError) -> ApiError {
    match e {
        QueryError::Threshold { name, reason } => ApiError::bad(format!("{name}: {reason}")),
        QueryError::Coarsen(c) => ApiError::bad(format!("coarsen: must be at most 10, got {c}")),
        QueryError::Outside { .. } => ApiError::bad("at: outside the map's key range"),
        other => other.into(),
    }
}

fn thresholds(q: &HashMap<String, String>) -> Result<ThresholdsIn, ApiError> {
    let get = |name: &str| match q.get(name) {
        None => Ok(None),
        Some(s) => {
            s.parse::<f64>().map(Some).map_err(|_| ApiError::bad(format!("{name}: {s:?} is not a number")))
        }
    };
    Ok(ThresholdsIn { p_free: get("p_free")?, p_occ: get("p_occ")?, var_max: get("var_max")? })
}

fn parse_num<T: std::str::FromStr>(q: &HashMap<String, String>, name: &str) -> Result<Option<T>, ApiError> {
    q.get(name)
        .map(|s| s.parse::<T>().map_err(|_| ApiError::bad(format!("{name}: {s:?} is not a valid number"))))
        .transpose()
}

fn parse_state(q: &HashMap<String, String>) -> Result<Option<CellState>, ApiError> {
    match q.get("state").map(String::as_str) {
        None => Ok(None),
        Some("free") => Ok(Some(CellState::Free)),
        Some("occupied") => Ok(Some(CellState::Occupied)),
        Some("unknown") => Ok(Some(CellState::Unknown)),
        Some(other) => Err(ApiError::bad(format!("state: {other:?} is not free|occupied|unknown"))),
    }
}

fn cells_refused(e: CellsError) -> ApiError {
    match e {
        CellsError::SinceAhead { since, version } => {
            ApiError::bad(format!("since: {since} is ahead of the map's version {version}"))
        }
        CellsError::SinceForgotten { history_from } => ApiError::gone(format!(
            "since: changes before version {history_from} are not known (the map was opened at that version); load the whole map"
        )),
        CellsError::CoarsenWithSince => {
            ApiError::bad(format!("coarsen: at most {} with since", crate::core::key::BLOCK_SHIFT))
        }
        CellsError::Query(e) => refused(e),
    }
}

/// Packs the answer (layout in the module docs).
fn encode_cells(version: u64, res: f64, answer: &CellsAnswer) -> Vec<u8> {
    let (cells, blocks): (&[BoxCell], &[BlockKey]) = (&answer.cells, &answer.blocks);
    let (n, m) = (cells.len(), blocks.len());
    let mut out = Vec::with_capacity(HEADER_BYTES + 32 * n + 12 * m);
    out.extend_from_slice(CELLS_MAGIC);
    for v in [CELLS_LAYOUT_VERSION, n as u32, m as u32] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&res.to_le_bytes());
    out.extend_from_slice(&u32::from(answer.coarsen).to_le_bytes());
    out.extend_from_slice(&BLOCK_EDGE.unsigned_abs().to_le_bytes());
    let edge_m = f64::from(BLOCK_EDGE) * res;
    let (lo, hi) = match answer.extent {
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
    State(st): State<AppState>,
    Path(map): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, ApiError> {
    let queries = st.service.queries(&map)?;
    let coarsen: u8 = parse_num(&q, "coarsen")?.unwrap_or(0);
    let state = parse_state(&q)?;
    let since: Option<u64> = parse_num(&q, "since")?;
    let th = queries.thresholds(thresholds(&q)?).map_err(refused)?;
    let request = CellsRequest { box_world: parse_box(&q)?, coarsen: u32::from(coarsen), state, th, since };
    let query = queries.cells(request).map_err(cells_refused)?;
    let body = offload::run(query.runs_inline(), move || {
        let answer = query.run().map_err(refused)?;
        Ok::<_, ApiError>(encode_cells(query.version(), query.resolution_m(), &answer))
    })
    .await??;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], body).into_response())
}

/// `GET /v1/maps/{map}/cell?at=x,y,z[&p_free=…&p_occ=…&var_max=…]`: the cell containing a
/// point, with its Beta posterior (α, β) besides probability, variance and state.
async fn cell(
    State(st): State<AppState>,
    Path(map): Path<String>,
    Query(q): Query<HashMap<String, String>>,
) -> Result<Response, ApiError> {
    let queries = st.service.queries(&map)?;
    let at = parse_xyz(q.get("at").map(String::as_str).unwrap_or(""), "at")?;
    let th = queries.thresholds(thresholds(&q)?).map_err(refused)?;
    let snap = queries.snapshot().clone();
    let mut answer = None;
    queries.points(vec![at], th).and_then(|p| p.run(|a| answer = Some(a))).map_err(refused)?;
    let a = answer.ok_or_else(|| ApiError::bad("at: outside the map's key range"))?;
    let params = snap.map.params();
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
async fn poses(State(st): State<AppState>, Path(map): Path<String>) -> Result<Response, ApiError> {
    let poses: Vec<_> = st.service.recent_poses(&map)?.iter().map(pose_json).collect();
    Ok(axum::Json(json!({ "poses": poses })).into_response())
}
