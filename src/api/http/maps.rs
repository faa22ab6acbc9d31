//! HTTP maps: `GET /v1/maps`, `GET /v1/maps/{map}` (parameters and statistics as JSON) and
//! `PUT /v1/maps/{map}` (create, parameters named like the `build` flags).

use super::{ApiError, ApiResult, AppState, parse};
use crate::core::{MapParams, RangeMode, Thresholds};
use crate::service::MapInfo;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use serde::Deserialize;
use serde_json::{Value, json};

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

pub(super) async fn list_maps(State(st): State<AppState>) -> ApiResult {
    let maps: Vec<Value> = st.service.list_maps().iter().map(info_json).collect();
    Ok(axum::Json(json!({ "maps": maps })).into_response())
}

pub(super) async fn get_map(State(st): State<AppState>, Path(map): Path<String>) -> ApiResult {
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

pub(super) async fn create_map(
    State(st): State<AppState>,
    Path(map): Path<String>,
    body: Bytes,
) -> ApiResult {
    let p: ParamsJson =
        if body.iter().all(u8::is_ascii_whitespace) { ParamsJson::default() } else { parse(&body)? };
    let info = st.service.create_map(&map, p.to_params()?)?;
    Ok((StatusCode::CREATED, axum::Json(info_json(&info))).into_response())
}
