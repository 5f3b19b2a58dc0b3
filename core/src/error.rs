//! The failures the core decides itself, and their wire codes.
//!
//! A round the core refuses (the scheduler's [`AdmitError`], a newer round of the task, a server
//! that drains) or fails (its batch lost with its engine and not run again, an internal
//! inconsistency) gets a [`RoundError`]; `From<&RoundError> for ErrorReply` is where the core's
//! failures get their wire codes. Failures of the transport, the validator and the engines are
//! the server's (`kairos_server::validation::RequestError`, which wraps this type).

use kairos_protocol::{ErrorCode, ErrorReply};

use crate::scheduler::{AdmitError, TaskId};

/// Why a batch was lost with its engine instance (the label of the re-dispatch counter).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum LossReason {
    /// The worker's connection closed or timed out (missed heartbeats, kill).
    ConnectionLost,
    /// The worker reset the batch's stream or finished it without an answer.
    StreamReset,
    /// The worker answered the batch with something unusable (wrong count or shapes,
    /// non-finite values, text over the protocol's limits): it was removed.
    InvalidAnswer,
    /// The batch's deadline passed without an answer.
    Deadline,
    /// The instance had left the pool before the batch could be sent.
    Gone,
}

impl LossReason {
    /// Every reason, for exporting counters.
    pub const ALL: [LossReason; 5] = [
        LossReason::ConnectionLost,
        LossReason::StreamReset,
        LossReason::InvalidAnswer,
        LossReason::Deadline,
        LossReason::Gone,
    ];

    /// The label, `snake_case`.
    pub fn as_str(self) -> &'static str {
        match self {
            LossReason::ConnectionLost => "connection_lost",
            LossReason::StreamReset => "stream_reset",
            LossReason::InvalidAnswer => "invalid_answer",
            LossReason::Deadline => "deadline",
            LossReason::Gone => "gone",
        }
    }
}

impl std::fmt::Display for LossReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Why the core refused or failed a round.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RoundError {
    /// The scheduler refused the request.
    #[error(transparent)]
    Admit(#[from] AdmitError),
    /// A pending request was replaced by a newer round of its task.
    #[error("round {round} was superseded by round {by}")]
    Superseded {
        /// The replaced round.
        round: u64,
        /// The newer round.
        by: u64,
    },
    /// The round's batch was lost with its engine instance, and the round was not run again
    /// (out of attempts or of time): retryable.
    #[error("engine {engine} was lost ({reason}): {detail}")]
    Lost {
        /// The instance.
        engine: String,
        /// Which way it was lost.
        reason: LossReason,
        /// Why the round was not run again.
        detail: String,
    },
    /// Something the server should never do happened (a chunk or an observation went missing).
    #[error("{0}")]
    Internal(String),
    /// The server is draining.
    #[error("the server is shutting down")]
    ShuttingDown,
}

impl RoundError {
    /// The wire code.
    pub fn code(&self) -> ErrorCode {
        match self {
            RoundError::Admit(e) => match e {
                AdmitError::Overloaded { .. } => ErrorCode::Overloaded,
                // One answer for all three, so a robot cannot learn which ids other robots use.
                AdmitError::Forbidden { .. }
                | AdmitError::UnknownTask { .. }
                | AdmitError::TaskEnded { .. } => ErrorCode::UnknownTask,
                AdmitError::RoundOutOfOrder { .. } | AdmitError::RoundInProgress { .. } => {
                    ErrorCode::RoundOutOfOrder
                }
                AdmitError::InvalidExecInfo(_) => ErrorCode::InvalidRequest,
            },
            RoundError::Superseded { .. } => ErrorCode::RoundOutOfOrder,
            RoundError::Lost { .. } | RoundError::Internal(_) => ErrorCode::Internal,
            RoundError::ShuttingDown => ErrorCode::ShuttingDown,
        }
    }
}

/// How long an overloaded client is asked to wait before retrying.
pub const OVERLOADED_RETRY_AFTER_MS: u32 = 50;

/// The text of every refusal that concerns a task the robot may not use, whether the id is
/// unknown, ended, or another robot's: one text (and one code, `unknown_task`), so that the
/// answer does not tell a robot which task ids exist.
pub fn task_not_open_message(task: TaskId) -> String {
    format!(
        "task {} is not open for this robot (unknown, ended, or another robot's)",
        task.0
    )
}

impl From<&RoundError> for ErrorReply {
    fn from(error: &RoundError) -> ErrorReply {
        let message = match error {
            RoundError::Admit(
                AdmitError::Forbidden { task }
                | AdmitError::UnknownTask { task }
                | AdmitError::TaskEnded { task },
            ) => task_not_open_message(*task),
            other => other.to_string(),
        };
        let mut reply = ErrorReply::new(error.code(), message);
        if matches!(error, RoundError::Admit(AdmitError::Overloaded { .. })) {
            reply.retry_after_ms = Some(OVERLOADED_RETRY_AFTER_MS);
        }
        reply
    }
}
