//! Runs synchronous service work from an async handler: inline when the work says it is cheap,
//! else on tokio's blocking pool, so heavy queries and edits never hold an async worker. The
//! decision is the service's ([`crate::service::query`]); every transport runs it here, so
//! they all move the same work off the runtime.
//!
//! Not a transport: it knows tokio, nothing of any wire format.

/// The blocking task died (it panicked); the transport answers INTERNAL / 500.
#[derive(Debug)]
pub struct TaskFailed(pub String);

/// Runs `f` on the calling task when `inline`, else on a blocking thread.
pub async fn run<T: Send + 'static>(
    inline: bool,
    f: impl FnOnce() -> T + Send + 'static,
) -> Result<T, TaskFailed> {
    if inline {
        return Ok(f());
    }
    blocking(f).await
}

/// Runs `f` on a blocking thread (work that waits, such as an edit waiting for the map's
/// writer, or streams through a channel, such as an export).
pub async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T, TaskFailed> {
    tokio::task::spawn_blocking(f).await.map_err(|e| TaskFailed(e.to_string()))
}

/// Starts `f` on a blocking thread without waiting for it (an export, which streams its
/// chunks through a channel the handler returns at once).
pub fn detach(f: impl FnOnce() + Send + 'static) {
    drop(tokio::task::spawn_blocking(f));
}
