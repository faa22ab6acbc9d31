//! gRPC `WatchUpdates`: the map's updates as a server stream of `bgkmap.v1.MapUpdate`.
//!
//! The stream starts with the catch-up (the blocks changed since the version asked for; none
//! when none was asked), then one message per change of the map (a batch of integrated scans,
//! a merge, a retraction, a re-pose). A watcher that falls behind the service's bounded ring
//! gets one `RESYNC` message listing every block changed since the last version it was sent.
//! When the server shuts down the stream ends with `UNAVAILABLE`; after a restart a version
//! from before it gets a catch-up with `reset`: every block the map holds, drop the rest.

use crate::api::proto::pb;
use crate::api::proto::updates::{update_to_pb, watch};
use crate::service::{MapService, Watch};
use std::pin::Pin;
use std::task::{Context, Poll};
use tonic::Status;

/// The `WatchUpdates` response stream.
#[derive(Debug)]
pub struct UpdateStream {
    watch: Watch,
    ended: bool,
}

impl tokio_stream::Stream for UpdateStream {
    type Item = Result<pb::MapUpdate, Status>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if self.ended {
            return Poll::Ready(None);
        }
        let resolution = self.watch.resolution_m;
        match self.watch.poll_update(cx) {
            Poll::Ready(Some(u)) => Poll::Ready(Some(Ok(update_to_pb(&u, resolution)))),
            Poll::Ready(None) => {
                self.ended = true;
                Poll::Ready(Some(Err(Status::unavailable("the server is shutting down; watch again"))))
            }
            Poll::Pending => Poll::Pending,
        }
    }
}

/// Validates the request and starts the watch.
pub(super) fn watch_updates(
    service: &MapService,
    req: pb::WatchUpdatesRequest,
) -> Result<UpdateStream, Status> {
    Ok(UpdateStream { watch: watch(service, &req)?, ended: false })
}
