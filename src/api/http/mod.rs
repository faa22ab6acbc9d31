//! HTTP JSON transport (axum), mirroring the gRPC calls under `/v1/…`, plus `/healthz`,
//! `/readyz` and `/metrics` (Prometheus text), the updates as server-sent events
//! ([`updates`]) and the web viewer ([`viewer`], its page and assets in
//! `src/api/http/viewer/`).
//!
//! Handlers parse the body themselves so a bad request gets a 400 whose message names the field
//! (serde's "missing field `seq`", or ours), convert, call one service function (queries: the
//! front door [`crate::service::query`], run where it says by `api::offload`), convert back.
//! Every error answer is `{"error": message}` with the status of [`crate::api::status`].
//!
//! Must not depend on the gRPC or zenoh transports.

mod edits;
mod maps;
mod metrics;
mod queries;
mod scans;
pub mod updates;
pub mod viewer;

use super::status::http_code;
use crate::service::query::cells::WorldBox;
use crate::service::{MapService, ServiceError};
use axum::Router;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde_json::json;
use std::collections::HashMap;
use std::sync::Arc;

/// HTTP limits (the query limits are the service's, see [`crate::service::QueryLimits`]).
#[derive(Debug, Clone)]
pub struct HttpConfig {
    /// Largest request body. Default 64 MiB.
    pub max_body_bytes: usize,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self { max_body_bytes: 64 << 20 }
    }
}

#[derive(Clone)]
struct AppState {
    service: Arc<MapService>,
    counters: Arc<metrics::Counters>,
}

/// An error answer: status code and a JSON body `{"error": message}`.
#[derive(Debug)]
pub struct ApiError(StatusCode, String);

impl ApiError {
    fn bad(msg: impl Into<String>) -> Self {
        Self(StatusCode::BAD_REQUEST, msg.into())
    }

    fn gone(msg: impl Into<String>) -> Self {
        Self(StatusCode::GONE, msg.into())
    }

    fn internal(msg: impl Into<String>) -> Self {
        Self(StatusCode::INTERNAL_SERVER_ERROR, msg.into())
    }
}

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        Self(StatusCode::from_u16(http_code(&e)).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR), e.to_string())
    }
}

impl From<crate::api::offload::TaskFailed> for ApiError {
    fn from(e: crate::api::offload::TaskFailed) -> Self {
        Self::internal(format!("query task failed: {}", e.0))
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

type ApiResult = Result<Response, ApiError>;

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
    let state = AppState { service, counters: Arc::default() };
    Router::new()
        .route("/healthz", get(|| async { "ok\n" }))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics::metrics))
        .route("/v1/maps", get(maps::list_maps))
        .route("/v1/maps/{map}", get(maps::get_map).put(maps::create_map))
        .route("/v1/maps/{map}/scans", post(scans::insert_scan))
        .route("/v1/maps/{map}/query/points", post(queries::points_query))
        .route("/v1/maps/{map}/query/box", post(queries::box_query))
        .route("/v1/maps/{map}/query/rays", post(queries::rays_query))
        .route("/v1/maps/{map}/merge", post(edits::merge))
        .route("/v1/maps/{map}/retract", post(edits::retract))
        .route("/v1/maps/{map}/repose", post(edits::repose))
        .layer(DefaultBodyLimit::max(limit))
        .with_state(state.clone())
        .merge(viewer::routes(state))
}

fn parse<T: serde::de::DeserializeOwned>(body: &Bytes) -> Result<T, ApiError> {
    serde_json::from_slice(body).map_err(|e| ApiError::bad(format!("invalid JSON body: {e}")))
}

/// Parses `x,y,z`.
fn parse_xyz(s: &str, name: &str) -> Result<[f64; 3], ApiError> {
    let v: Vec<f64> = s.split(',').filter_map(|t| t.trim().parse().ok()).collect();
    <[f64; 3]>::try_from(v.as_slice())
        .ok()
        .filter(|v| v.iter().all(|c| c.is_finite()))
        .ok_or_else(|| ApiError::bad(format!("{name}: expected three finite numbers x,y,z, got {s:?}")))
}

/// `min=x,y,z&max=x,y,z` (both or neither).
fn parse_box(q: &HashMap<String, String>) -> Result<Option<WorldBox>, ApiError> {
    match (q.get("min"), q.get("max")) {
        (None, None) => Ok(None),
        (Some(a), Some(b)) => Ok(Some((parse_xyz(a, "min")?, parse_xyz(b, "max")?))),
        _ => Err(ApiError::bad("min and max go together")),
    }
}
