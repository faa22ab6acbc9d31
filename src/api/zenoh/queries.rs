//! The queryables: `bgkmap/<map>/query/points`, `…/query/box`, `…/query/rays` answer the gRPC
//! request messages (`QueryPointsRequest`, `QueryBoxRequest`, `CastRaysRequest`, in the query
//! payload) with the gRPC response messages, through the same [`ProtoCalls`] as gRPC; and
//! `bgkmap/<map>/ingest` takes a `Scan` and replies `InsertScanResponse` once it is durable in
//! the map's journal (`bgkmap/<map>/ingest?wait_applied`: once it is integrated), like gRPC
//! `InsertScan`; `bgkmap/<map>/updates/since` takes a `WatchUpdatesRequest` and replies the
//! `MapUpdate` catch-up (see [`super::updates`]).
//!
//! The map is the key's; a request's own `map` field may be empty or must name the same map.
//! A failure is one `reply_err` whose payload is UTF-8 text `<GRPC_CODE>: <message>`, the code
//! and message gRPC would have sent (`INVALID_ARGUMENT: bgkmap.v1.QueryPointsRequest.xyz_f32: …`).

use super::ZenohError;
use super::ingest::{IngestContext, parse_key};
use crate::api::proto::calls::ProtoCalls;
use crate::api::proto::codec::encode_to_vec;
use crate::api::proto::pb;
use prost::Message;
use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use tonic::Status;
use zenoh::bytes::Encoding;
use zenoh::query::{Query, Queryable};

/// Counts the query handlers running, so shutdown can wait for them; spawns them on the
/// server's runtime.
#[derive(Debug, Clone)]
pub struct InFlight {
    count: Arc<AtomicUsize>,
    runtime: tokio::runtime::Handle,
}

impl InFlight {
    pub fn new(count: Arc<AtomicUsize>, runtime: tokio::runtime::Handle) -> Self {
        Self { count, runtime }
    }

    fn spawn(&self, task: impl Future<Output = ()> + Send + 'static) {
        self.count.fetch_add(1, Ordering::AcqRel);
        let count = self.count.clone();
        self.runtime.spawn(async move {
            task.await;
            count.fetch_sub(1, Ordering::AcqRel);
        });
    }
}

/// The kinds of query, by key.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Points,
    Box,
    Rays,
    Ingest,
    UpdatesSince,
}

impl Kind {
    const ALL: [Kind; 5] = [Kind::Points, Kind::Box, Kind::Rays, Kind::Ingest, Kind::UpdatesSince];

    fn key(self) -> &'static str {
        match self {
            Kind::Points => "bgkmap/*/query/points",
            Kind::Box => "bgkmap/*/query/box",
            Kind::Rays => "bgkmap/*/query/rays",
            Kind::Ingest => "bgkmap/*/ingest",
            Kind::UpdatesSince => "bgkmap/*/updates/since",
        }
    }
}

/// Request messages that name their map.
trait MapRequest: Message + Default {
    const NAME: &'static str;
    fn map_mut(&mut self) -> &mut String;
}

macro_rules! map_request {
    ($t:ty, $name:literal) => {
        impl MapRequest for $t {
            const NAME: &'static str = $name;
            fn map_mut(&mut self) -> &mut String {
                &mut self.map
            }
        }
    };
}
map_request!(pb::QueryPointsRequest, "QueryPointsRequest");
map_request!(pb::QueryBoxRequest, "QueryBoxRequest");
map_request!(pb::CastRaysRequest, "CastRaysRequest");
map_request!(pb::WatchUpdatesRequest, "WatchUpdatesRequest");

/// Declares the five queryables (not complete: another process may serve other maps).
pub async fn declare(
    session: &zenoh::Session,
    ctx: Arc<IngestContext>,
    flight: InFlight,
) -> Result<Vec<Queryable<()>>, ZenohError> {
    let mut out = Vec::new();
    for kind in Kind::ALL {
        let (ctx, flight) = (ctx.clone(), flight.clone());
        let q = session
            .declare_queryable(kind.key())
            .complete(false)
            .callback(move |query| {
                let ctx = ctx.clone();
                flight.spawn(async move { answer(kind, &ctx, query).await });
            })
            .await
            .map_err(|e| ZenohError::declare(kind.key(), e))?;
        out.push(q);
    }
    Ok(out)
}

/// The payload of a query, refused beyond the message limit.
fn payload(query: &Query, limit: usize) -> Result<Vec<u8>, Status> {
    let bytes = query.payload().map(|p| p.to_bytes().into_owned()).unwrap_or_default();
    if bytes.len() > limit {
        return Err(Status::resource_exhausted(format!(
            "message of {} bytes exceeds the limit of {limit} bytes (max_message_bytes)",
            bytes.len()
        )));
    }
    Ok(bytes)
}

/// The request of a query to `map`: decoded, its `map` filled in or checked.
fn request<R: MapRequest>(map: &str, bytes: &[u8]) -> Result<R, Status> {
    let mut req = R::decode(bytes)
        .map_err(|e| Status::invalid_argument(format!("malformed protobuf bgkmap.v1.{}: {e}", R::NAME)))?;
    let named = req.map_mut();
    if named.is_empty() {
        *named = map.to_string();
    } else if named != map {
        return Err(Status::invalid_argument(format!(
            "bgkmap.v1.{}.map: {named:?} differs from the key's map {map:?}",
            R::NAME
        )));
    }
    Ok(req)
}

async fn call(kind: Kind, ctx: &IngestContext, query: &Query) -> Result<Vec<u8>, Status> {
    let key = query.key_expr().as_str();
    let parsed = match kind {
        Kind::Ingest => parse_key(key, "ingest"),
        Kind::UpdatesSince => parse_key(key, "updates"),
        _ => parse_key(key, "query"),
    };
    let Some((map, _)) = parsed else {
        return Err(Status::invalid_argument(format!("key {key:?} must name one map: bgkmap/<map>/…")));
    };
    let calls: &ProtoCalls = &ctx.calls;
    let bytes = payload(query, calls.max_message_bytes())?;
    Ok(match kind {
        Kind::Points => encode_to_vec(&calls.query_points(request(map, &bytes)?).await?),
        Kind::Box => encode_to_vec(&calls.query_box(request(map, &bytes)?).await?),
        Kind::Rays => encode_to_vec(&calls.cast_rays(request(map, &bytes)?).await?),
        Kind::Ingest => ctx.ingest_query(map, &bytes, wait_applied(query)).await?,
        Kind::UpdatesSince => {
            let req: pb::WatchUpdatesRequest = request(map, &bytes)?;
            crate::api::proto::updates::changes_since(calls.service(), &req)?.encode_to_vec()
        }
    })
}

/// The selector parameter `wait_applied` (bare, `=true` or `=1`) of an ingest query.
fn wait_applied(query: &Query) -> bool {
    query.parameters().get("wait_applied").is_some_and(|v| matches!(v, "" | "true" | "1"))
}

/// `INVALID_ARGUMENT`-style name of a gRPC code.
pub fn code_name(code: tonic::Code) -> String {
    let camel = format!("{code:?}");
    let mut out = String::with_capacity(camel.len() + 4);
    for (i, c) in camel.chars().enumerate() {
        if c.is_ascii_uppercase() && i > 0 {
            out.push('_');
        }
        out.push(c.to_ascii_uppercase());
    }
    out
}

async fn answer(kind: Kind, ctx: &IngestContext, query: Query) {
    let sent = match call(kind, ctx, &query).await {
        Ok(bytes) => {
            query.reply(query.key_expr().clone(), bytes).encoding(Encoding::APPLICATION_PROTOBUF).await
        }
        Err(status) => {
            let text = format!("{}: {}", code_name(status.code()), status.message());
            query.reply_err(text).encoding(Encoding::TEXT_PLAIN).await
        }
    };
    // A querier that timed out or left cannot be answered; nothing else to do.
    drop(sent);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_named_as_grpc_names_them() {
        assert_eq!(code_name(tonic::Code::InvalidArgument), "INVALID_ARGUMENT");
        assert_eq!(code_name(tonic::Code::ResourceExhausted), "RESOURCE_EXHAUSTED");
        assert_eq!(code_name(tonic::Code::NotFound), "NOT_FOUND");
        assert_eq!(code_name(tonic::Code::Ok), "OK");
    }

    #[test]
    fn requests_take_the_key_map_or_must_agree_with_it() {
        let named = pb::QueryPointsRequest { map: "a".into(), ..Default::default() }.encode_to_vec();
        assert_eq!(request::<pb::QueryPointsRequest>("a", &named).unwrap().map, "a");
        assert!(request::<pb::QueryPointsRequest>("b", &named).unwrap_err().message().contains("differs"));
        assert_eq!(request::<pb::QueryBoxRequest>("b", &[]).unwrap().map, "b");
        let e = request::<pb::CastRaysRequest>("b", &[0x0a, 0x05, 0x61]).unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert!(e.message().starts_with("malformed protobuf bgkmap.v1.CastRaysRequest"), "{}", e.message());
    }
}
