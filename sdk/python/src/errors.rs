//! The Python exception classes, and [`ClientError`] → exception.
//!
//! Every exception derives from `kairos.KairosError`. Errors the server answered with carry its
//! wire code (`docs/PROTOCOL.md`, error codes) as `.code` and whether a retry may succeed as
//! `.retryable`; client-side errors have `.code` None.

#![allow(missing_docs)] // create_exception! generates undocumentable items; the .pyi documents them.

use kairos_sdk::client::ClientError;
use kairos_sdk::protocol::{ErrorCode, ValidationError};
use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;

create_exception!(
    kairos,
    KairosError,
    PyException,
    "Base class of the Kairos client's errors."
);
create_exception!(
    kairos,
    ConnectionFailed,
    KairosError,
    "The server could not be reached, or the connection was lost and reconnecting failed."
);
create_exception!(
    kairos,
    Timeout,
    ConnectionFailed,
    "Connecting or a round took longer than its limit."
);
create_exception!(
    kairos,
    Unauthorized,
    KairosError,
    "The server refused the robot token."
);
create_exception!(
    kairos,
    PinMismatch,
    KairosError,
    "The server's certificate is not the pinned one."
);
create_exception!(
    kairos,
    InvalidObservation,
    KairosError,
    "The observation does not fit the model or the limits; the message names the field."
);
create_exception!(
    kairos,
    InvalidRequest,
    KairosError,
    "Another argument or request field is invalid."
);
create_exception!(
    kairos,
    Overloaded,
    KairosError,
    "The server is at capacity or shutting down; retry later."
);
create_exception!(
    kairos,
    ServerError,
    KairosError,
    "The server failed the request."
);
create_exception!(
    kairos,
    ProtocolError,
    KairosError,
    "The server broke the protocol, or speaks another version."
);
create_exception!(
    kairos,
    TaskError,
    KairosError,
    "The call does not fit the task's state (no task, or a round already in flight)."
);

/// Adds the exception classes to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("KairosError", py.get_type::<KairosError>())?;
    m.add("ConnectionFailed", py.get_type::<ConnectionFailed>())?;
    m.add("Timeout", py.get_type::<Timeout>())?;
    m.add("Unauthorized", py.get_type::<Unauthorized>())?;
    m.add("PinMismatch", py.get_type::<PinMismatch>())?;
    m.add("InvalidObservation", py.get_type::<InvalidObservation>())?;
    m.add("InvalidRequest", py.get_type::<InvalidRequest>())?;
    m.add("Overloaded", py.get_type::<Overloaded>())?;
    m.add("ServerError", py.get_type::<ServerError>())?;
    m.add("ProtocolError", py.get_type::<ProtocolError>())?;
    m.add("TaskError", py.get_type::<TaskError>())?;
    Ok(())
}

/// The exception for a wire error code.
fn for_code(code: ErrorCode, message: String) -> PyErr {
    match code {
        ErrorCode::InvalidObservation => InvalidObservation::new_err(message),
        ErrorCode::Unauthorized => Unauthorized::new_err(message),
        ErrorCode::Overloaded | ErrorCode::ShuttingDown => Overloaded::new_err(message),
        ErrorCode::UnsupportedVersion | ErrorCode::BadFrame => ProtocolError::new_err(message),
        ErrorCode::TooLarge
        | ErrorCode::InvalidRequest
        | ErrorCode::Forbidden
        | ErrorCode::UnknownTask
        | ErrorCode::RoundOutOfOrder
        | ErrorCode::UnknownPolicy => InvalidRequest::new_err(message),
        ErrorCode::Internal => ServerError::new_err(message),
        // The server stopped reading an upload that fell under its minimum rate: a slow link.
        ErrorCode::TooSlow => Timeout::new_err(message),
    }
}

/// The Python exception for `error`.
pub fn client_error(py: Python<'_>, error: ClientError) -> PyErr {
    let message = error.to_string();
    let (err, code, retryable) = match &error {
        ClientError::Server(reply) => (
            for_code(reply.code, message),
            Some(reply.code.as_str()),
            reply.retryable,
        ),
        ClientError::Invalid(validation) => {
            let code = validation.code();
            // A size limit broken by the observation is a bad observation, as the server says.
            let err = match validation {
                ValidationError::TooLarge { field, .. } if field.starts_with("observation") => {
                    InvalidObservation::new_err(message)
                }
                _ => for_code(code, message),
            };
            (err, Some(code.as_str()), false)
        }
        ClientError::Unauthorized(_) => (
            Unauthorized::new_err(message),
            Some(ErrorCode::Unauthorized.as_str()),
            false,
        ),
        ClientError::PinMismatch { .. } => (PinMismatch::new_err(message), None, false),
        ClientError::VersionMismatch { .. }
        | ClientError::Protocol(_)
        | ClientError::StreamReset(_)
        | ClientError::Encode(_) => (ProtocolError::new_err(message), None, false),
        ClientError::Timeout { .. } => (Timeout::new_err(message), None, true),
        ClientError::Connection(_) => {
            let retryable = error.is_retryable();
            (ConnectionFailed::new_err(message), None, retryable)
        }
        ClientError::Tls(_)
        | ClientError::Bind(_)
        | ClientError::Connect(_)
        | ClientError::Closed
        | ClientError::Runtime(_) => (ConnectionFailed::new_err(message), None, false),
    };
    let value = err.value(py);
    // Setting attributes on a fresh exception instance cannot fail short of memory exhaustion.
    let _ = value.setattr("code", code);
    let _ = value.setattr("retryable", retryable);
    err
}
