//! The one mapping from service errors to gRPC codes and HTTP statuses.

use crate::service::ServiceError;

/// gRPC status for a service error. Messages name the field or the map.
pub fn to_grpc(e: &ServiceError) -> tonic::Status {
    use tonic::Code;
    let code = match e {
        ServiceError::NotFound(_) => Code::NotFound,
        ServiceError::AlreadyExists(_) => Code::AlreadyExists,
        ServiceError::InvalidArgument { .. } => Code::InvalidArgument,
        ServiceError::Busy { .. } => Code::ResourceExhausted,
        ServiceError::ShuttingDown => Code::Unavailable,
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

/// HTTP status code for a service error.
pub fn http_code(e: &ServiceError) -> u16 {
    match e {
        ServiceError::NotFound(_) => 404,
        ServiceError::AlreadyExists(_) => 409,
        ServiceError::InvalidArgument { .. } => 400,
        ServiceError::Busy { .. } => 429,
        ServiceError::ShuttingDown => 503,
        ServiceError::Storage(_) => 500,
    }
}
