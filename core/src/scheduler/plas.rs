//! Autellix PLAS (Program-Level Attained Service; Luo et al., "Autellix: An Efficient Serving
//! Engine for LLM Agents as General Programs", arXiv 2502.13965, §4.2), the paper's second
//! baseline, with a robot task as the "program" and one round's generation as one "call".
//!
//! What Autellix does, and how it maps here:
//! - A call's priority is its program's *attained service*: the total engine time its earlier
//!   calls received. Here: [`PendingView::attained_service`] = Σ|G| of the task.
//! - Priorities are discretised into `K` queues `Q_0 … Q_{K-1}` whose service ranges grow
//!   exponentially, and a call *enters* the queue matching its program's service (unlike MLFQ,
//!   where every new call starts at the top). Within a queue calls are served FIFO. Autellix's
//!   per-call quantum demotion is moot here: a round's generation is one non-preemptible forward
//!   pass, so a call never runs across a decision.
//! - Anti-starvation: a program whose total waiting time is at least `β ×` its total service is
//!   promoted to the top queue. Waiting time here is queueing only ([`PendingView::queued`]),
//!   since Autellix knows nothing of robot execution.
//!
//! Exact semantics (a plugin twin must reproduce them), all times in whole microseconds:
//! 1. Thresholds: `T_0 = q`, `T_i = T_{i-1} + q·g^i` (saturating `u64` arithmetic), for
//!    `i = 0 … K−2`. The queue of a service `s` is the number of thresholds `≤ s` (so queue 0
//!    covers `[0, q)`, queue 1 `[q, q + q·g)`, …, queue `K−1` is unbounded).
//! 2. Starving iff `(queued as f64) >= β · (max(q, s) as f64)` (`f64` product); a starving
//!    request goes to queue 0. The `max(q, ·)` keeps a task with no service yet from counting as
//!    starving after any wait at all (Autellix floors the service the same way).
//! 3. Order by `(queue, arrived_at, request)` ascending.
//!
//! Parameters and defaults: `queues` K = 8; `quantum_ms` q = 1000 (about 1–10 rounds of
//! generation for the models of docs/ENGINE.md, so the first queue holds tasks that are just
//! starting); `growth` g = 2 (exponentially growing ranges, as in Autellix: 1, 3, 7, … 127 s);
//! `beta` β = 8. The Autellix paper defines the mechanism but its numeric defaults could not be
//! retrieved here; β = 8 is the FastServe-derived value of the public vLLM reimplementation
//! (kungfu-team/autellix, `plas_scheduler.py`), whose doubling thresholds we also follow.

use super::RequestId;
use super::policy::{PendingView, PolicyError, PriorityPolicy, order_by_key};
use crate::time::{Timestamp, duration_micros};

/// PLAS configuration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlasConfig {
    /// Number of queues `K` (≥ 1).
    pub queues: u32,
    /// Width of the first queue `q`, in microseconds (≥ 1).
    pub quantum_us: u64,
    /// Growth factor `g` of successive queue widths (≥ 1).
    pub growth: u32,
    /// Anti-starvation ratio `β` (finite, > 0).
    pub beta: f64,
}

impl Default for PlasConfig {
    fn default() -> Self {
        PlasConfig {
            queues: 8,
            quantum_us: 1_000_000,
            growth: 2,
            beta: 8.0,
        }
    }
}

/// Autellix PLAS.
#[derive(Clone, Debug)]
pub struct Plas {
    config: PlasConfig,
    thresholds: Vec<u64>,
    scratch: Vec<((u32, Timestamp, RequestId), usize)>,
}

impl Plas {
    /// A PLAS policy; `config` is assumed valid (see [`super::registry`] for validation).
    pub fn new(config: PlasConfig) -> Self {
        let mut thresholds = Vec::new();
        let mut width = config.quantum_us.max(1);
        let mut total = 0u64;
        for _ in 1..config.queues.max(1) {
            total = total.saturating_add(width);
            thresholds.push(total);
            width = width.saturating_mul(u64::from(config.growth.max(1)));
        }
        Plas {
            config,
            thresholds,
            scratch: Vec::new(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &PlasConfig {
        &self.config
    }

    /// The queue (0 = highest priority) a request lands in (steps 1–2 of the module doc).
    pub fn queue_of(&self, view: &PendingView) -> u32 {
        let service = duration_micros(view.attained_service);
        let queued = duration_micros(view.queued) as f64;
        let floor = service.max(self.config.quantum_us.max(1)) as f64;
        if queued >= self.config.beta * floor {
            return 0;
        }
        let crossed = self.thresholds.partition_point(|&t| t <= service);
        u32::try_from(crossed).unwrap_or(u32::MAX)
    }
}

impl PriorityPolicy for Plas {
    fn name(&self) -> &str {
        "plas"
    }

    fn order(
        &mut self,
        _now: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        let mut scratch = std::mem::take(&mut self.scratch);
        order_by_key(pending, order, &mut scratch, |v| {
            (self.queue_of(v), v.arrived_at, v.request)
        });
        self.scratch = scratch;
        Ok(())
    }
}
