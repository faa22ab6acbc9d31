//! The one mapping from service errors to gRPC codes and HTTP statuses.
//!
//! | error | gRPC | HTTP |
//! |---|---|---|
//! | unknown map / scans | `NOT_FOUND` | 404 |
//! | map exists | `ALREADY_EXISTS` | 409 |
//! | bad request | `INVALID_ARGUMENT` | 400 |
//! | queue full | `RESOURCE_EXHAUSTED` (+ `retry-after-ms`) | 429 (+ `Retry-After`) |
//! | map read-only after a failed write, or damaged | `UNAVAILABLE` | 503 |
//! | cannot be done exactly (raw scans pruned, conflicting scans) | `FAILED_PRECONDITION` | 412 |
//! | corrupt block or journal record | `DATA_LOSS` | 500 |
//! | shutting down | `UNAVAILABLE` | 503 |
//! | other storage failure | `INTERNAL` | 500 |

use crate::service::ServiceError;

/// gRPC status for a service error. Messages name the field or the map.
pub fn to_grpc(e: &ServiceError) -> tonic::Status {
    use tonic::Code;
    let code = match e {
        ServiceError::NotFound(_) | ServiceError::ScansNotFound(_) => Code::NotFound,
        ServiceError::AlreadyExists(_) => Code::AlreadyExists,
        ServiceError::InvalidArgument { .. } => Code::InvalidArgument,
        ServiceError::Busy { .. } => Code::ResourceExhausted,
        ServiceError::ReadOnly { .. } | ServiceError::ShuttingDown => Code::Unavailable,
        ServiceError::Precondition(_) => Code::FailedPrecondition,
        ServiceError::DataLoss(_) => Code::DataLoss,
        ServiceError::Storage(_) => Code::Internal,
    };
    let mut status = tonic::Status::new(code, e.to_string());
    if let ServiceError::Busy { retry_after_ms, .. } = e
        && let Ok(v) = retry_after_ms.to_string().parse()
    {
        status.metadata_mut().insert("retry-after-ms", v);
    }
    status
}

/// The wait a busy refusal asks for (its `retry-after-ms`); `None` for any other status.
pub fn retry_after(s: &tonic::Status) -> Option<std::time::Duration> {
    let ms = s.metadata().get("retry-after-ms")?.to_str().ok()?.parse().ok()?;
    Some(std::time::Duration::from_millis(ms))
}

/// HTTP status code for a service error.
pub fn http_code(e: &ServiceError) -> u16 {
    match e {
        ServiceError::NotFound(_) | ServiceError::ScansNotFound(_) => 404,
        ServiceError::AlreadyExists(_) => 409,
        ServiceError::Precondition(_) => 412,
        ServiceError::InvalidArgument { .. } => 400,
        ServiceError::Busy { .. } => 429,
        ServiceError::ReadOnly { .. } | ServiceError::ShuttingDown => 503,
        ServiceError::DataLoss(_) | ServiceError::Storage(_) => 500,
    }
}
