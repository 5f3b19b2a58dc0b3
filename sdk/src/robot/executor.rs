//! [`ChunkExecutor`]: the execution rules of the module docs ([`super`]) with time as an
//! argument. Pure: no clock, no I/O, no async runtime.

use crate::protocol::LastExecInfo;

/// The chunk being executed.
#[derive(Clone, Debug)]
struct ActiveChunk {
    round: u64,
    actions: Vec<Vec<f32>>,
    /// Index of the first executable action (the number discarded on arrival).
    first: usize,
    /// Index of the next action to execute.
    next: usize,
    started_at_us: Option<u64>,
    /// Actions the robot executed between the capture of the chunk's observation and its
    /// arrival (the round's actual `d`).
    delay: u32,
}

impl ActiveChunk {
    fn executable(&self) -> usize {
        self.actions.len() - self.first
    }

    fn executed(&self) -> usize {
        self.next - self.first
    }

    fn remaining(&self) -> usize {
        self.actions.len() - self.next
    }
}

#[derive(Clone, Copy, Debug)]
struct Pending {
    round: u64,
    executed_at_capture: u64,
}

/// Where a robot starts executing a chunk that arrives (module docs, "Alignment").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Alignment {
    /// At the robot's own count of the actions it executed since the chunk's observation was
    /// captured: exact, whatever the server predicted.
    #[default]
    Executed,
    /// At the reply's `start`, the server's prediction of that count (the robot's own count
    /// when the server sends none).
    ServerStart,
}

/// How a new chunk was applied.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ChunkApplied {
    /// Actions of the new chunk discarded because their time had passed.
    pub discarded: u32,
    /// Actions of the new chunk that will execute (0 if it was entirely stale).
    pub executable: u32,
    /// The chunk that stopped executing because of this one: (round, actions executed, actions
    /// dropped unexecuted). `None` if no chunk was executing (none yet, or it had run out).
    pub replaced: Option<(u64, u32, u32)>,
}

/// One action to execute.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionStep<'a> {
    /// The round whose chunk it comes from.
    pub round: u64,
    /// Its index in that chunk.
    pub index: u32,
    /// The action vector.
    pub action: &'a [f32],
    /// True if it is the chunk's last action.
    pub last_of_chunk: bool,
}

/// The execution rules of the module docs, with time as an argument (sans-IO).
#[derive(Clone, Debug)]
pub struct ChunkExecutor {
    control_hz: f32,
    trigger: f32,
    alignment: Alignment,
    chunk: Option<ActiveChunk>,
    executed_total: u64,
    pending: Option<Pending>,
}

impl ChunkExecutor {
    /// An executor for a robot at `control_hz` that requests at `trigger` ∈ [0, 1].
    pub fn new(control_hz: f32, trigger: f32) -> ChunkExecutor {
        ChunkExecutor {
            control_hz,
            trigger: trigger.clamp(0.0, 1.0),
            alignment: Alignment::default(),
            chunk: None,
            executed_total: 0,
            pending: None,
        }
    }

    /// The same executor aligning arriving chunks by `alignment`.
    pub fn with_alignment(mut self, alignment: Alignment) -> ChunkExecutor {
        self.alignment = alignment;
        self
    }

    /// The robot's control rate, actions per second.
    pub fn control_hz(&self) -> f32 {
        self.control_hz
    }

    /// Actions executed since the task began.
    pub fn executed_total(&self) -> u64 {
        self.executed_total
    }

    /// Actions queued for execution.
    pub fn remaining(&self) -> usize {
        self.chunk.as_ref().map_or(0, ActiveChunk::remaining)
    }

    /// Whether a request is in flight.
    pub fn in_flight(&self) -> bool {
        self.pending.is_some()
    }

    /// The round of the request in flight, if one is.
    pub fn in_flight_round(&self) -> Option<u64> {
        self.pending.map(|pending| pending.round)
    }

    /// Whether the next request is due: none in flight, and the current chunk has reached the
    /// trigger or run out.
    pub fn wants_request(&self) -> bool {
        if self.pending.is_some() {
            return false;
        }
        match &self.chunk {
            None => true,
            Some(chunk) => {
                let trigger_point = (self.trigger * chunk.executable() as f32).ceil() as usize;
                chunk.remaining() == 0 || chunk.executed() >= trigger_point
            }
        }
    }

    /// Records that round `round` was requested now, with an observation captured now. Returns
    /// the Last Exec Info to send with it.
    pub fn request_sent(&mut self, round: u64, now_us: u64) -> Option<LastExecInfo> {
        self.pending = Some(Pending {
            round,
            executed_at_capture: self.executed_total,
        });
        self.last_exec(now_us)
    }

    /// Last Exec Info describing the current (or last) chunk at `now_us`.
    pub fn last_exec(&self, now_us: u64) -> Option<LastExecInfo> {
        self.chunk.as_ref().map(|chunk| LastExecInfo {
            exec_started_at_us: chunk.started_at_us.unwrap_or(now_us),
            actions_remaining: u32::try_from(chunk.remaining()).unwrap_or(u32::MAX),
            control_hz: self.control_hz,
            round: Some(chunk.round),
            delay: Some(chunk.delay),
        })
    }

    /// Records that the in-flight round's observation was replaced by one captured now.
    pub fn observation_refreshed(&mut self) {
        if let Some(pending) = &mut self.pending {
            pending.executed_at_capture = self.executed_total;
        }
    }

    /// Records that the in-flight request failed; the next one may be sent.
    pub fn request_failed(&mut self) {
        self.pending = None;
    }

    /// Applies the chunk of `round` that arrived now, aligned by the robot's own count.
    pub fn reply_arrived(&mut self, round: u64, actions: Vec<Vec<f32>>) -> ChunkApplied {
        self.reply_arrived_from(round, actions, None)
    }

    /// Applies the chunk of `round` that arrived now; `server_start` is the reply's `start`,
    /// which [`Alignment::ServerStart`] follows.
    pub fn reply_arrived_from(
        &mut self,
        round: u64,
        actions: Vec<Vec<f32>>,
        server_start: Option<u32>,
    ) -> ChunkApplied {
        let executed_at_capture = match self.pending.take() {
            Some(pending) if pending.round == round => Some(pending.executed_at_capture),
            // A reply nobody waits for: treat its observation as captured now.
            _ => None,
        };
        let since_capture =
            executed_at_capture.map_or(0, |at| self.executed_total.saturating_sub(at));
        let own = usize::try_from(since_capture).unwrap_or(usize::MAX);
        let first = match (self.alignment, server_start) {
            (Alignment::ServerStart, Some(start)) => usize::try_from(start).unwrap_or(usize::MAX),
            // A reply nobody waits for has no capture to count from: the server's index.
            (Alignment::Executed, Some(start)) if executed_at_capture.is_none() => {
                usize::try_from(start).unwrap_or(usize::MAX)
            }
            _ => own,
        };
        let discarded = first.min(actions.len());
        let as_u32 = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        if discarded == actions.len() {
            return ChunkApplied {
                discarded: as_u32(discarded),
                executable: 0,
                replaced: None,
            };
        }
        // A chunk that already ran out ended then; only one still executing is replaced.
        let replaced = self
            .chunk
            .take()
            .filter(|old| old.remaining() > 0)
            .map(|old| (old.round, as_u32(old.executed()), as_u32(old.remaining())));
        let executable = actions.len() - discarded;
        self.chunk = Some(ActiveChunk {
            round,
            actions,
            first: discarded,
            next: discarded,
            started_at_us: None,
            delay: u32::try_from(since_capture).unwrap_or(u32::MAX),
        });
        ChunkApplied {
            discarded: as_u32(discarded),
            executable: as_u32(executable),
            replaced,
        }
    }

    /// The action to execute now, if any.
    pub fn next_action(&mut self, now_us: u64) -> Option<ActionStep<'_>> {
        let chunk = self.chunk.as_mut()?;
        if chunk.remaining() == 0 {
            return None;
        }
        let index = chunk.next;
        chunk.next += 1;
        chunk.started_at_us.get_or_insert(now_us);
        self.executed_total += 1;
        let last_of_chunk = chunk.remaining() == 0;
        Some(ActionStep {
            round: chunk.round,
            index: u32::try_from(index).unwrap_or(u32::MAX),
            action: &chunk.actions[index],
            last_of_chunk,
        })
    }

    /// Drops what is left of the current chunk (the task ended before it ran out). Returns the
    /// chunk's round, how many of its actions executed and how many were dropped, if any were.
    pub fn drop_rest(&mut self) -> Option<(u64, u32, u32)> {
        let chunk = self.chunk.take().filter(|c| c.remaining() > 0)?;
        let as_u32 = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        Some((
            chunk.round,
            as_u32(chunk.executed()),
            as_u32(chunk.remaining()),
        ))
    }

    /// The current chunk's round and how many of its actions executed.
    pub fn current_chunk(&self) -> Option<(u64, u32)> {
        self.chunk.as_ref().map(|chunk| {
            (
                chunk.round,
                u32::try_from(chunk.executed()).unwrap_or(u32::MAX),
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(round: u64, len: usize) -> Vec<Vec<f32>> {
        (0..len).map(|i| vec![round as f32, i as f32]).collect()
    }

    #[test]
    fn first_request_is_immediate_and_has_no_exec_info() {
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        assert!(executor.wants_request());
        assert_eq!(executor.request_sent(0, 100), None);
        assert!(!executor.wants_request(), "one request in flight at a time");
    }

    #[test]
    fn trigger_fires_at_the_executed_fraction() {
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        executor.request_sent(0, 0);
        let applied = executor.reply_arrived(0, chunk(0, 10));
        assert_eq!(
            applied,
            ChunkApplied {
                discarded: 0,
                executable: 10,
                replaced: None
            }
        );
        for i in 0..5 {
            assert!(!executor.wants_request(), "not yet after {i} actions");
            let step = executor.next_action(1000 + i).unwrap();
            assert_eq!(step.index as u64, i);
        }
        assert!(executor.wants_request());
        let info = executor.request_sent(1, 2000).unwrap();
        assert_eq!(info.exec_started_at_us, 1000);
        assert_eq!(info.actions_remaining, 5);
        assert_eq!(info.control_hz, 10.0);
    }

    #[test]
    fn arrival_discards_the_actions_whose_time_passed_and_replaces_the_rest() {
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 8));
        for t in 0..4 {
            executor.next_action(t);
        }
        executor.request_sent(1, 4);
        // Three more actions execute while round 1 is generated.
        for t in 4..7 {
            executor.next_action(t);
        }
        let applied = executor.reply_arrived(1, chunk(1, 8));
        assert_eq!(applied.discarded, 3);
        assert_eq!(applied.executable, 5);
        assert_eq!(applied.replaced, Some((0, 7, 1)));
        let step = executor.next_action(7).unwrap();
        assert_eq!((step.round, step.index), (1, 3));
        assert_eq!(step.action, &[1.0, 3.0]);
    }

    /// Last Exec Info names the chunk's round and its actual d; `ServerStart` follows the
    /// reply's start index, `Executed` the robot's own count, and a reply nobody waited for takes
    /// the server's index either way.
    #[test]
    fn alignment_follows_the_own_count_or_the_servers_start() {
        let run = |alignment: Alignment, start: Option<u32>| {
            let mut executor = ChunkExecutor::new(10.0, 0.5).with_alignment(alignment);
            executor.request_sent(0, 0);
            executor.reply_arrived(0, chunk(0, 8));
            executor.next_action(0);
            executor.request_sent(1, 1);
            // Two actions while round 1 is in flight: its actual d is 2.
            executor.next_action(1);
            executor.next_action(2);
            let applied = executor.reply_arrived_from(1, chunk(1, 8), start);
            let info = executor.last_exec(3).unwrap();
            (applied.discarded, info.round, info.delay)
        };
        assert_eq!(run(Alignment::Executed, Some(3)), (2, Some(1), Some(2)));
        assert_eq!(run(Alignment::ServerStart, Some(3)), (3, Some(1), Some(2)));
        assert_eq!(run(Alignment::ServerStart, None), (2, Some(1), Some(2)));
        let mut executor = ChunkExecutor::new(10.0, 0.5);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 8));
        // Round 5 was never requested here (a reply to a round resent after a reconnect).
        assert_eq!(
            executor
                .reply_arrived_from(5, chunk(5, 8), Some(4))
                .discarded,
            4
        );
        let info = executor.last_exec(10).unwrap();
        assert_eq!((info.round, info.delay), (Some(5), Some(0)));
    }

    #[test]
    fn a_refetch_moves_the_alignment_point() {
        let mut executor = ChunkExecutor::new(10.0, 0.0);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 8));
        executor.request_sent(1, 0);
        executor.next_action(0);
        executor.next_action(1);
        executor.observation_refreshed();
        executor.next_action(2);
        assert_eq!(executor.reply_arrived(1, chunk(1, 8)).discarded, 1);
    }

    #[test]
    fn an_entirely_stale_chunk_keeps_the_old_one_and_asks_again() {
        let mut executor = ChunkExecutor::new(10.0, 0.0);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 10));
        executor.request_sent(1, 0);
        for t in 0..4 {
            executor.next_action(t);
        }
        let applied = executor.reply_arrived(1, chunk(1, 3));
        assert_eq!(
            applied,
            ChunkApplied {
                discarded: 3,
                executable: 0,
                replaced: None
            }
        );
        assert_eq!(executor.remaining(), 6);
        assert!(executor.wants_request());
        assert_eq!(executor.next_action(4).unwrap().round, 0);
    }

    #[test]
    fn an_idle_robot_discards_nothing() {
        let mut executor = ChunkExecutor::new(10.0, 1.0);
        executor.request_sent(0, 0);
        executor.reply_arrived(0, chunk(0, 2));
        executor.next_action(0);
        executor.next_action(1);
        assert!(executor.next_action(2).is_none());
        assert!(executor.wants_request());
        let info = executor.request_sent(1, 5).unwrap();
        assert_eq!(info.actions_remaining, 0);
        assert_eq!(info.exec_started_at_us, 0);
        let applied = executor.reply_arrived(1, chunk(1, 4));
        assert_eq!(applied.discarded, 0);
        assert_eq!(
            applied.replaced, None,
            "the old chunk ended when it ran out"
        );
    }

    #[test]
    fn trigger_one_is_synchronous_and_zero_is_immediate() {
        let mut sync = ChunkExecutor::new(10.0, 1.0);
        sync.request_sent(0, 0);
        sync.reply_arrived(0, chunk(0, 3));
        sync.next_action(0);
        sync.next_action(1);
        assert!(!sync.wants_request());
        sync.next_action(2);
        assert!(sync.wants_request());

        let mut eager = ChunkExecutor::new(10.0, 0.0);
        eager.request_sent(0, 0);
        eager.reply_arrived(0, chunk(0, 3));
        assert!(eager.wants_request());
    }
}
