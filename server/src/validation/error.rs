//! [`RequestError`]: the one error type a connection task answers with, and
//! `From<&RequestError> for ErrorReply`, the one place that picks wire codes for the server's
//! own failures (the core's are [`RoundError`]'s, which this wraps).

use kairos_core::action::PolicyLookupError;
use kairos_core::error::RoundError;
use kairos_core::scheduler::AdmitError;
use kairos_engine::EngineError;
use kairos_sdk::protocol::{ErrorCode, ErrorReply, FrameError, PROTOCOL_VERSION, ValidationError};

use crate::pool::PoolError;

/// Every way a request can fail, from the first byte to the reply.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    /// The bytes are not a valid frame or message.
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// A field breaks the protocol's limits or rules.
    #[error(transparent)]
    Protocol(#[from] ValidationError),
    /// The observation does not fit the served model.
    #[error("invalid observation: {field}: {reason}")]
    Observation {
        /// Which field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// Another field is inconsistent.
    #[error("invalid request: {field}: {reason}")]
    Invalid {
        /// Which field.
        field: String,
        /// What is wrong.
        reason: String,
    },
    /// A message of the wrong kind at this point of the exchange.
    #[error("unexpected {got} message, expected {expected}")]
    UnexpectedMessage {
        /// What the exchange needs here.
        expected: &'static str,
        /// What arrived.
        got: String,
    },
    /// The horizon policy is unknown or its parameters are invalid.
    #[error(transparent)]
    Policy(#[from] PolicyLookupError),
    /// The client speaks no protocol version this server does.
    #[error("protocol version {0} is not supported (this server speaks {PROTOCOL_VERSION})")]
    UnsupportedVersion(u32),
    /// The token matches no configured robot.
    #[error("unknown token")]
    Unauthorized,
    /// Generation failed.
    #[error(transparent)]
    Engine(#[from] PoolError),
    /// The request's frame arrived slower than `[connections] min_upload_bytes_per_s`
    /// (the reason says how slow).
    #[error("{0}")]
    TooSlow(String),
    /// The core refused or failed the round (admission, superseded, lost, draining).
    #[error(transparent)]
    Round(#[from] RoundError),
    /// Over a round rate of `[connections]`: `who` ("this connection", "robot `a`") sent
    /// rounds faster than `limit` (the key) allows. Retryable after `retry_after`.
    #[error(
        "rate limited: {who} is over [connections] {limit}; retry in {} ms",
        retry_after_ms(*.retry_after)
    )]
    RateLimited {
        /// Whose rounds.
        who: String,
        /// The configuration key of the rate.
        limit: &'static str,
        /// How long until a round would be taken.
        retry_after: std::time::Duration,
    },
}

/// `wait` in whole ms for the wire's `retry_after_ms` (at least 1, saturating).
fn retry_after_ms(wait: std::time::Duration) -> u32 {
    u32::try_from(wait.as_millis()).unwrap_or(u32::MAX).max(1)
}

impl From<AdmitError> for RequestError {
    fn from(error: AdmitError) -> RequestError {
        RequestError::Round(RoundError::Admit(error))
    }
}

impl RequestError {
    /// The server is draining: new rounds are refused.
    pub const SHUTTING_DOWN: RequestError = RequestError::Round(RoundError::ShuttingDown);

    /// A failure that is the server's, not the request's.
    pub fn internal(message: impl Into<String>) -> RequestError {
        RequestError::Round(RoundError::Internal(message.into()))
    }

    /// The wire code.
    pub fn code(&self) -> ErrorCode {
        match self {
            RequestError::Frame(e) => e.code(),
            RequestError::Protocol(e) => e.code(),
            RequestError::Observation { .. } => ErrorCode::InvalidObservation,
            RequestError::Invalid { .. } => ErrorCode::InvalidRequest,
            RequestError::UnexpectedMessage { .. } => ErrorCode::BadFrame,
            RequestError::Policy(PolicyLookupError::Unknown { .. }) => ErrorCode::UnknownPolicy,
            RequestError::Policy(PolicyLookupError::Params { .. }) => ErrorCode::InvalidRequest,
            RequestError::UnsupportedVersion(_) => ErrorCode::UnsupportedVersion,
            RequestError::Unauthorized => ErrorCode::Unauthorized,
            // A request the model refused is the request's fault (defence in depth: validation
            // checks everything the engine would refuse); any other engine failure is ours.
            RequestError::Engine(PoolError::Engine {
                source: EngineError::InvalidInput(_),
                ..
            }) => ErrorCode::InvalidObservation,
            RequestError::Engine(_) => ErrorCode::Internal,
            RequestError::TooSlow(_) => ErrorCode::TooSlow,
            RequestError::Round(e) => e.code(),
            RequestError::RateLimited { .. } => ErrorCode::Overloaded,
        }
    }
}

impl From<&RequestError> for ErrorReply {
    fn from(error: &RequestError) -> ErrorReply {
        match error {
            RequestError::Round(round) => ErrorReply::from(round),
            RequestError::RateLimited { retry_after, .. } => ErrorReply {
                retry_after_ms: Some(retry_after_ms(*retry_after)),
                ..ErrorReply::new(error.code(), error.to_string())
            },
            other => ErrorReply::new(other.code(), other.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use kairos_core::error::OVERLOADED_RETRY_AFTER_MS;
    use kairos_core::scheduler::TaskId;

    use super::*;

    #[test]
    fn a_task_that_is_not_the_robots_gets_one_answer_whatever_the_reason() {
        let task = TaskId(42);
        let replies: Vec<ErrorReply> = [
            AdmitError::Forbidden { task },
            AdmitError::UnknownTask { task },
            AdmitError::TaskEnded { task },
        ]
        .into_iter()
        .map(|e| ErrorReply::from(&RequestError::from(e)))
        .collect();
        assert_eq!(replies[0].code, ErrorCode::UnknownTask);
        assert!(replies.iter().all(|r| *r == replies[0]), "{replies:?}");
    }

    #[test]
    fn an_engine_refusal_is_the_requests_fault_and_a_crash_is_ours() {
        let refused = RequestError::Engine(PoolError::Engine {
            engine: "e".into(),
            source: EngineError::InvalidInput("state[0]: NaN".into()),
        });
        assert_eq!(refused.code(), ErrorCode::InvalidObservation);
        assert!(!ErrorReply::from(&refused).retryable);
        let crashed = RequestError::Engine(PoolError::Panicked {
            engine: "e".into(),
            message: "bug".into(),
        });
        assert_eq!(crashed.code(), ErrorCode::Internal);
        assert!(ErrorReply::from(&crashed).retryable);
    }

    #[test]
    fn admit_errors_map_to_their_wire_codes() {
        let cases = [
            (AdmitError::Overloaded { pending: 3 }, ErrorCode::Overloaded),
            (
                AdmitError::Forbidden { task: TaskId(1) },
                ErrorCode::UnknownTask,
            ),
            (
                AdmitError::UnknownTask { task: TaskId(1) },
                ErrorCode::UnknownTask,
            ),
            (
                AdmitError::TaskEnded { task: TaskId(1) },
                ErrorCode::UnknownTask,
            ),
            (
                AdmitError::RoundOutOfOrder { last: 3, got: 2 },
                ErrorCode::RoundOutOfOrder,
            ),
            (
                AdmitError::InvalidExecInfo("x".into()),
                ErrorCode::InvalidRequest,
            ),
        ];
        for (admit, expected) in cases {
            let reply = ErrorReply::from(&RequestError::from(admit));
            assert_eq!(reply.code, expected);
            assert_eq!(reply.retryable, expected == ErrorCode::Overloaded);
        }
        let overloaded =
            ErrorReply::from(&RequestError::from(AdmitError::Overloaded { pending: 1 }));
        assert_eq!(overloaded.retry_after_ms, Some(OVERLOADED_RETRY_AFTER_MS));
        assert_eq!(
            ErrorReply::from(&RequestError::Unauthorized).code,
            ErrorCode::Unauthorized
        );
    }

    #[test]
    fn a_rate_limited_round_is_overloaded_with_the_wait() {
        let limited = |wait| {
            ErrorReply::from(&RequestError::RateLimited {
                who: "robot `a`".into(),
                limit: "rounds_per_s_per_robot",
                retry_after: wait,
            })
        };
        let reply = limited(std::time::Duration::from_millis(2_500));
        assert_eq!(reply.code, ErrorCode::Overloaded);
        assert!(reply.retryable);
        assert_eq!(reply.retry_after_ms, Some(2_500));
        assert!(reply.message.contains("robot `a`"), "{}", reply.message);
        assert!(reply.message.contains("rounds_per_s_per_robot"));
        // Never "retry in 0 ms", never an overflow.
        assert_eq!(limited(std::time::Duration::ZERO).retry_after_ms, Some(1));
        assert_eq!(
            limited(std::time::Duration::MAX).retry_after_ms,
            Some(u32::MAX)
        );
    }
}
