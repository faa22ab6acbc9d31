//! `GET /metrics`: Prometheus text of every map's ingest and storage figures and the HTTP
//! query counters.

use super::AppState;
use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use std::sync::atomic::{AtomicU64, Ordering};

/// HTTP queries answered and their time, per kind (points, box, rays).
#[derive(Debug, Default)]
pub(super) struct Counters {
    queries: [AtomicU64; 3],
    query_micros: [AtomicU64; 3],
}

impl Counters {
    /// Counts one query of `kind` started at `t0`.
    pub(super) fn count(&self, kind: usize, t0: std::time::Instant) {
        self.queries[kind].fetch_add(1, Ordering::Relaxed);
        self.query_micros[kind].fetch_add(t0.elapsed().as_micros() as u64, Ordering::Relaxed);
    }
}

pub(super) async fn metrics(State(st): State<AppState>) -> Response {
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
