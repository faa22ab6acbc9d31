//! gRPC `CreateMap`, `ListMaps` and `GetMap`, and the map parameters and statistics as
//! protobuf (unset parameters take the compiled-in defaults; errors name the field).

use crate::api::proto::convert::{bad, service_err};
use crate::api::proto::pb;
use crate::core::{MapParams, RangeMode, Thresholds};
use crate::service::{MapInfo, MapService};
use tonic::Status;

pub(super) fn create_map(service: &MapService, req: pb::CreateMapRequest) -> Result<pb::MapInfo, Status> {
    let params = map_params(req.params)?;
    let info = service.create_map(&req.map, params).map_err(service_err)?;
    Ok(map_info_to_pb(info))
}

pub(super) fn list_maps(service: &MapService) -> pb::ListMapsResponse {
    pb::ListMapsResponse { maps: service.list_maps().into_iter().map(map_info_to_pb).collect() }
}

pub(super) fn get_map(service: &MapService, req: pb::GetMapRequest) -> Result<pb::MapInfo, Status> {
    service.map_info(&req.map).map(map_info_to_pb).map_err(service_err)
}

fn map_params(p: Option<pb::MapParams>) -> Result<MapParams, Status> {
    let p = p.unwrap_or_default();
    let d = MapParams::default();
    let range_mode = match p.range_mode.as_deref() {
        None => d.range_mode,
        Some(s) => s.parse::<RangeMode>().map_err(|e| bad("MapParams.range_mode", e.reason))?,
    };
    let params = MapParams {
        resolution_m: p.resolution.unwrap_or(d.resolution_m),
        sf2: p.sf2.unwrap_or(d.sf2),
        ell_m: p.ell.unwrap_or(d.ell_m),
        free_resolution_m: p.free_resolution.unwrap_or(d.free_resolution_m),
        ds_resolution_m: p.ds_resolution.unwrap_or(d.ds_resolution_m),
        max_range_m: p.max_range.unwrap_or(d.max_range_m),
        range_mode,
        prior_a: p.prior_a.unwrap_or(d.prior_a),
        prior_b: p.prior_b.unwrap_or(d.prior_b),
        origin_as_free: d.origin_as_free,
        sub_cells: p.sub_cells.unwrap_or(d.sub_cells),
        thresholds: Thresholds {
            p_free: p.p_free.unwrap_or(d.thresholds.p_free),
            p_occ: p.p_occ.unwrap_or(d.thresholds.p_occ),
            var_max: p.var_max.unwrap_or(d.thresholds.var_max),
        },
    };
    params.validate().map_err(|e| bad(&format!("MapParams.{}", e.name), e.reason))?;
    Ok(params)
}

fn map_params_to_pb(p: &MapParams) -> pb::MapParams {
    pb::MapParams {
        resolution: Some(p.resolution_m),
        sf2: Some(p.sf2),
        ell: Some(p.ell_m),
        free_resolution: Some(p.free_resolution_m),
        ds_resolution: Some(p.ds_resolution_m),
        max_range: Some(p.max_range_m),
        range_mode: Some(p.range_mode.as_str().to_string()),
        prior_a: Some(p.prior_a),
        prior_b: Some(p.prior_b),
        p_free: Some(p.thresholds.p_free),
        p_occ: Some(p.thresholds.p_occ),
        var_max: Some(p.thresholds.var_max),
        sub_cells: Some(p.sub_cells),
    }
}

fn map_info_to_pb(info: MapInfo) -> pb::MapInfo {
    pb::MapInfo {
        params: Some(map_params_to_pb(&info.params)),
        map: info.name,
        version: info.version,
        blocks: info.blocks as u64,
        cells_with_evidence: info.cells_with_evidence as u64,
        queued: info.queued as u64,
        scans: info.scans,
        journal_bytes: info.journal_bytes,
        corrupt_blocks: info.corrupt_blocks as u64,
        read_only: info.read_only.unwrap_or_default(),
        sources: info
            .sources
            .into_iter()
            .map(|(source, s)| pb::SourceStats {
                source,
                received: s.received,
                applied: s.applied,
                duplicates: s.duplicates,
                rejected: s.rejected,
                highest_seq: s.highest_seq,
                pending: s.pending,
                gaps: s.gaps,
                pruned: s.pruned,
                retracted: s.retracted,
                dropped_points: s.dropped_points,
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_default_when_unset_and_round_trip() {
        assert_eq!(map_params(None).unwrap(), MapParams::default());
        let p = MapParams { max_range_m: 5.0, range_mode: RangeMode::Drop, ..MapParams::default() };
        assert_eq!(map_params(Some(map_params_to_pb(&p))).unwrap(), p);
        let e = map_params(Some(pb::MapParams { ell: Some(-1.0), ..Default::default() })).unwrap_err();
        assert!(e.message().starts_with("bgkmap.v1.MapParams.ell: "), "{}", e.message());
        let e = map_params(Some(pb::MapParams { range_mode: Some("x".into()), ..Default::default() }))
            .unwrap_err();
        assert!(e.message().starts_with("bgkmap.v1.MapParams.range_mode: "), "{}", e.message());
    }
}
