//! Task traces: what one robot did on one task, recorded in isolation, for replay at scale.
//!
//! The paper's evaluation (§5.1) records every task once, alone on the server, and then replays
//! many recordings concurrently: each replayed robot issues its round requests at the *recorded
//! action index*, so the work a task asks for is the same whatever the load, and only the waiting
//! changes. This module is the file format of such recordings (documented, with the replay rule,
//! in `docs/TRACES.md`), its reader and writer, and a [`TraceRecorder`] that turns a robot's
//! per-round events into a trace.
//!
//! A trace file is JSON Lines: the first line is a [`TraceHeader`], every further line one
//! [`TaskTrace`]. One task is one robot working through one instruction under one horizon
//! setting (the horizon policy and its parameters); the same task recorded under two settings
//! is two lines with the same `task` id and different `setting` labels.

use std::collections::BTreeMap;
use std::io::{BufRead, Write};

use serde::{Deserialize, Serialize};

/// The `format` field every trace header carries.
pub const TRACE_FORMAT: &str = "kairos-trace";

/// The trace format version this crate writes. Readers accept exactly this version; a future
/// version gets a new number and a converter rather than a silent reinterpretation.
pub const TRACE_VERSION: u32 = 1;

/// Largest chunk a trace may describe (bounds the per-round confidence vector).
pub const MAX_CHUNK_LEN: u32 = 4096;

/// First line of a trace file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TraceHeader {
    /// Always [`TRACE_FORMAT`].
    pub format: String,
    /// Always [`TRACE_VERSION`] for files this crate writes.
    pub version: u32,
    /// Where the rounds came from.
    pub source: TraceSource,
    /// Workload name (for generated traces: the workload file's `name`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub workload: Option<String>,
    /// Generator seed, for generated traces.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    /// Software that wrote the file, e.g. `kairos-sdk/0.1.0`.
    pub created_by: String,
}

impl TraceHeader {
    /// A header for the current format version.
    pub fn new(source: TraceSource) -> Self {
        TraceHeader {
            format: TRACE_FORMAT.to_string(),
            version: TRACE_VERSION,
            source,
            workload: None,
            seed: None,
            created_by: concat!("kairos-sdk/", env!("CARGO_PKG_VERSION")).to_string(),
        }
    }
}

/// Where a trace's rounds came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TraceSource {
    /// Recorded from a robot (or simulator) talking to a live server.
    Recorded,
    /// Generated from a workload description; modelled, not measured.
    Generated,
}

/// The horizon policy a task ran under, as named in the request's horizon selection.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HorizonSetting {
    /// Policy name, e.g. `static` or `threshold`.
    pub policy: String,
    /// Its parameters, e.g. `{"h": 10}` or `{"t": 0.4, "h_min": 5}`.
    #[serde(default)]
    pub params: BTreeMap<String, f64>,
}

/// One task, recorded in isolation under one horizon setting.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TaskTrace {
    /// Task id within the trace set. The same id under several settings is the same task.
    pub task: u64,
    /// Free-form task label (suite and task name), for humans.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<String>,
    /// Label of the horizon setting, e.g. `static` or `dynamic`; selects a variant on replay.
    pub setting: String,
    /// The horizon policy the task ran under.
    pub horizon: HorizonSetting,
    /// Actions executed per second.
    pub control_hz: f32,
    /// Actions per generated chunk (`N`).
    pub chunk_len: u32,
    /// Actions the robot executed from start to finish.
    pub total_actions: u32,
    /// The rounds, in order.
    pub rounds: Vec<RoundTrace>,
}

/// One round of a task: one request and the chunk that answered it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RoundTrace {
    /// Task-wide action index at which the request was issued: how many actions the robot had
    /// executed when it sent the request (0 for the first round). Replay issues the request at
    /// this index, whatever the load.
    pub issued_at_action: u32,
    /// Task-wide action index the chunk's action 0 corresponds to, when that is later than
    /// `issued_at_action`: the server re-fetched a fresher observation while the request queued,
    /// and the chunk was generated from that one. Absent means `issued_at_action`. The simulator
    /// replays the chunk at this alignment whatever the load (the replayed work is the
    /// recording's); validation uses it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aligned_at_action: Option<u32>,
    /// The horizon `H` the recorded setting chose for this round's chunk.
    pub horizon: u32,
    /// Actions of this chunk the robot executed (after discarding the actions whose time had
    /// passed when the chunk arrived).
    pub executed: u32,
    /// Generation latency on the server, measured in isolation, microseconds.
    pub gen_latency_us: u64,
    /// Request sent to reply received at the robot, in isolation, microseconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub round_trip_us: Option<u64>,
    /// Bytes of the observation sent with the request.
    pub obs_bytes: u32,
    /// Per action of the chunk (`chunk_len` values): the norm of its final diffusion update
    /// divided by the mean norm of its earlier updates — all the §3.1 threshold policy reads.
    /// With it, the horizon of any threshold setting can be recomputed on replay.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence: Option<Vec<f32>>,
}

impl RoundTrace {
    /// The action index the chunk's action 0 corresponds to (see `aligned_at_action`).
    pub fn aligned_at_action(&self) -> u32 {
        self.aligned_at_action.unwrap_or(self.issued_at_action)
    }
}

/// Why a trace could not be read, written or recorded.
#[derive(Debug, thiserror::Error)]
pub enum TraceError {
    /// Reading or writing the file failed.
    #[error("trace I/O failed")]
    Io(#[from] std::io::Error),
    /// A line is not valid JSON for its record type.
    #[error("line {line} is not a valid trace record")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// The JSON error.
        source: serde_json::Error,
    },
    /// The file is not a Kairos trace, or is of an unsupported version.
    #[error("unsupported trace: {0}")]
    Unsupported(String),
    /// A record is well-formed JSON but describes an impossible task.
    #[error("task {task} ({setting}): {reason}")]
    Invalid {
        /// The task id.
        task: u64,
        /// Its setting label.
        setting: String,
        /// What is wrong.
        reason: String,
    },
    /// The recorder was used out of order (a round before a task began, ...).
    #[error("recorder misuse: {0}")]
    Recorder(String),
    /// Serialising a record failed.
    #[error("cannot encode trace record: {0}")]
    Encode(serde_json::Error),
}

impl TaskTrace {
    /// Checks that the task can be replayed: positive frequency, non-empty rounds, request
    /// indices that never go backwards, never leave the robot with nothing to execute before the
    /// next request, and a last chunk that reaches the end of the task.
    pub fn validate(&self) -> Result<(), TraceError> {
        let invalid = |reason: String| TraceError::Invalid {
            task: self.task,
            setting: self.setting.clone(),
            reason,
        };
        if !(self.control_hz.is_finite() && self.control_hz > 0.0) {
            return Err(invalid(format!(
                "control_hz must be positive, got {}",
                self.control_hz
            )));
        }
        if self.chunk_len == 0 || self.chunk_len > MAX_CHUNK_LEN {
            return Err(invalid(format!(
                "chunk_len must be in 1..={MAX_CHUNK_LEN}, got {}",
                self.chunk_len
            )));
        }
        if self.total_actions == 0 {
            return Err(invalid("total_actions is 0".into()));
        }
        let Some(first) = self.rounds.first() else {
            return Err(invalid("no rounds".into()));
        };
        if first.issued_at_action != 0 {
            return Err(invalid(format!(
                "the first round must be issued at action 0, not {}",
                first.issued_at_action
            )));
        }
        let mut covered = 0u32;
        for (i, r) in self.rounds.iter().enumerate() {
            let aligned = r.aligned_at_action();
            if aligned < r.issued_at_action {
                return Err(invalid(format!(
                    "round {i}: aligned at action {aligned} before it was issued ({})",
                    r.issued_at_action
                )));
            }
            if r.horizon == 0 || r.horizon > self.chunk_len {
                return Err(invalid(format!(
                    "round {i}: horizon {} outside 1..={}",
                    r.horizon, self.chunk_len
                )));
            }
            if r.executed > r.horizon {
                return Err(invalid(format!(
                    "round {i}: executed {} > horizon {}",
                    r.executed, r.horizon
                )));
            }
            if i > 0 {
                let prev = &self.rounds[i - 1];
                if r.issued_at_action < prev.issued_at_action {
                    return Err(invalid(format!(
                        "round {i}: issued at action {} before round {} ({})",
                        r.issued_at_action,
                        i - 1,
                        prev.issued_at_action
                    )));
                }
                if r.issued_at_action > covered {
                    return Err(invalid(format!(
                        "round {i}: issued at action {} but the earlier chunks only reach {covered}",
                        r.issued_at_action
                    )));
                }
            }
            if let Some(c) = &r.confidence {
                if c.len() != self.chunk_len as usize {
                    return Err(invalid(format!(
                        "round {i}: {} confidence values for chunk_len {}",
                        c.len(),
                        self.chunk_len
                    )));
                }
                if c.iter().any(|v| !v.is_finite() || *v < 0.0) {
                    return Err(invalid(format!(
                        "round {i}: confidence values must be finite and >= 0"
                    )));
                }
            }
            covered = covered.max(aligned.saturating_add(r.horizon));
        }
        if covered < self.total_actions {
            return Err(invalid(format!(
                "the chunks reach action {covered}, short of total_actions {}",
                self.total_actions
            )));
        }
        Ok(())
    }

    /// Seconds the task takes with no waiting at all: its actions at the control frequency.
    pub fn execution_seconds(&self) -> f64 {
        f64::from(self.total_actions) / f64::from(self.control_hz)
    }
}

/// Writes a trace file: the header first, then one task per line.
pub struct TraceWriter<W: Write> {
    out: W,
}

impl<W: Write> TraceWriter<W> {
    /// Starts a file by writing its header.
    pub fn new(mut out: W, header: &TraceHeader) -> Result<Self, TraceError> {
        write_line(&mut out, header)?;
        Ok(TraceWriter { out })
    }

    /// Validates and appends one task.
    pub fn write_task(&mut self, task: &TaskTrace) -> Result<(), TraceError> {
        task.validate()?;
        write_line(&mut self.out, task)
    }

    /// Flushes and returns the underlying writer.
    pub fn finish(mut self) -> Result<W, TraceError> {
        self.out.flush()?;
        Ok(self.out)
    }
}

fn write_line<W: Write, T: Serialize>(out: &mut W, value: &T) -> Result<(), TraceError> {
    serde_json::to_writer(&mut *out, value).map_err(TraceError::Encode)?;
    out.write_all(b"\n")?;
    Ok(())
}

/// A whole trace file in memory.
#[derive(Clone, Debug, PartialEq)]
pub struct TraceSet {
    /// The header.
    pub header: TraceHeader,
    /// Every task line, in file order.
    pub tasks: Vec<TaskTrace>,
}

impl TraceSet {
    /// Reads and validates a whole trace file. Blank lines are skipped.
    pub fn read<R: BufRead>(input: R) -> Result<Self, TraceError> {
        let mut header: Option<TraceHeader> = None;
        let mut tasks = Vec::new();
        for (i, line) in input.lines().enumerate() {
            let line = line?;
            if line.trim().is_empty() {
                continue;
            }
            let number = i + 1;
            match &header {
                None => {
                    let h: TraceHeader =
                        serde_json::from_str(&line).map_err(|source| TraceError::Parse {
                            line: number,
                            source,
                        })?;
                    if h.format != TRACE_FORMAT {
                        return Err(TraceError::Unsupported(format!(
                            "format `{}` is not `{TRACE_FORMAT}`",
                            h.format
                        )));
                    }
                    if h.version != TRACE_VERSION {
                        return Err(TraceError::Unsupported(format!(
                            "version {} (this build reads version {TRACE_VERSION})",
                            h.version
                        )));
                    }
                    header = Some(h);
                }
                Some(_) => {
                    let t: TaskTrace =
                        serde_json::from_str(&line).map_err(|source| TraceError::Parse {
                            line: number,
                            source,
                        })?;
                    t.validate()?;
                    tasks.push(t);
                }
            }
        }
        let header = header.ok_or_else(|| TraceError::Unsupported("empty file".into()))?;
        Ok(TraceSet { header, tasks })
    }

    /// Writes the whole set.
    pub fn write<W: Write>(&self, out: W) -> Result<W, TraceError> {
        let mut w = TraceWriter::new(out, &self.header)?;
        for t in &self.tasks {
            w.write_task(t)?;
        }
        w.finish()
    }

    /// The distinct setting labels present, sorted.
    pub fn settings(&self) -> Vec<String> {
        let mut s: Vec<String> = self.tasks.iter().map(|t| t.setting.clone()).collect();
        s.sort();
        s.dedup();
        s
    }

    /// The tasks recorded under `setting`, in file order.
    pub fn variant<'a>(&'a self, setting: &'a str) -> impl Iterator<Item = &'a TaskTrace> + 'a {
        self.tasks.iter().filter(move |t| t.setting == setting)
    }
}

/// What the robot runtime reports about one round, identified by its round id. A recorder fed
/// these produces the same [`RoundTrace`]s the runtime experienced.
#[derive(Clone, Debug, PartialEq)]
pub enum RoundEvent {
    /// The robot sent the request of a new round.
    Requested {
        /// The round id (strictly increasing within the task).
        round: u64,
        /// Actions executed in the task so far (the round's `issued_at_action`).
        at_action: u32,
        /// Robot clock, µs.
        sent_at_us: u64,
        /// Bytes of the observation sent.
        obs_bytes: u32,
    },
    /// The server asked for a fresher observation before dispatch and got one captured after
    /// `at_action` actions of the task: the chunk will correspond to that index.
    Refetched {
        /// The round id.
        round: u64,
        /// Actions executed in the task when the fresh observation was captured.
        at_action: u32,
    },
    /// The reply arrived.
    Replied {
        /// The round id.
        round: u64,
        /// Robot clock, µs.
        received_at_us: u64,
        /// The horizon the server chose.
        horizon: u32,
        /// Server-reported generation time (the forward pass), µs.
        inference_us: u64,
        /// The per-action confidence ratios, if the runtime had them.
        confidence: Option<Vec<f32>>,
    },
    /// The robot stopped executing this round's chunk (a newer chunk replaced it, the chunk
    /// arrived with nothing left to execute, or the task ended) after executing `executed` of its
    /// actions.
    ChunkDone {
        /// The round id.
        round: u64,
        /// Actions of the chunk executed.
        executed: u32,
    },
}

/// Describes the task a recorder is about to record.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskMeta {
    /// Task id.
    pub task: u64,
    /// Human label.
    pub label: Option<String>,
    /// Setting label (`static`, `dynamic`, ...).
    pub setting: String,
    /// The horizon policy requested.
    pub horizon: HorizonSetting,
    /// Control frequency.
    pub control_hz: f32,
    /// Chunk length of the served model.
    pub chunk_len: u32,
}

#[derive(Debug)]
struct OpenRound {
    round: u64,
    issued_at_action: u32,
    aligned_at_action: Option<u32>,
    sent_at_us: u64,
    obs_bytes: u32,
    reply: Option<(u32, u64, u64, Option<Vec<f32>>)>,
    executed: Option<u32>,
}

/// One task being recorded: collects [`RoundEvent`]s (rounds overlap under asynchronous
/// inference, so events of several rounds interleave) and produces its [`TaskTrace`].
#[derive(Debug)]
pub struct TaskRecording {
    /// The task's description (its `chunk_len` may be filled in once the first reply shows it).
    pub meta: TaskMeta,
    rounds: Vec<OpenRound>,
}

impl TaskRecording {
    /// Starts recording a task.
    pub fn new(meta: TaskMeta) -> Self {
        TaskRecording {
            meta,
            rounds: Vec::new(),
        }
    }

    /// Feeds one event. Events must name a round the recording has seen requested (and, for
    /// `ChunkDone`, answered); a new request must carry a larger round id than the last.
    pub fn record(&mut self, event: RoundEvent) -> Result<(), TraceError> {
        match event {
            RoundEvent::Requested {
                round,
                at_action,
                sent_at_us,
                obs_bytes,
            } => {
                if self.rounds.last().is_some_and(|r| r.round >= round) {
                    return Err(TraceError::Recorder(format!(
                        "round {round} requested after a later or equal round"
                    )));
                }
                self.rounds.push(OpenRound {
                    round,
                    issued_at_action: at_action,
                    aligned_at_action: None,
                    sent_at_us,
                    obs_bytes,
                    reply: None,
                    executed: None,
                });
            }
            RoundEvent::Refetched { round, at_action } => {
                let r = self.open(round)?;
                if r.reply.is_some() {
                    return Err(TraceError::Recorder(format!(
                        "round {round} re-fetched after its reply"
                    )));
                }
                if at_action < r.issued_at_action {
                    return Err(TraceError::Recorder(format!(
                        "round {round} re-fetched at action {at_action}, before it was issued at {}",
                        r.issued_at_action
                    )));
                }
                r.aligned_at_action = Some(at_action);
            }
            RoundEvent::Replied {
                round,
                received_at_us,
                horizon,
                inference_us,
                confidence,
            } => {
                let r = self.open(round)?;
                if r.reply.is_some() {
                    return Err(TraceError::Recorder(format!("round {round} replied twice")));
                }
                r.reply = Some((horizon, received_at_us, inference_us, confidence));
            }
            RoundEvent::ChunkDone { round, executed } => {
                let r = self.open(round)?;
                if r.reply.is_none() {
                    return Err(TraceError::Recorder(format!(
                        "round {round} done before its reply"
                    )));
                }
                r.executed = Some(executed);
            }
        }
        Ok(())
    }

    fn open(&mut self, round: u64) -> Result<&mut OpenRound, TraceError> {
        self.rounds
            .iter_mut()
            .rev()
            .find(|r| r.round == round)
            .ok_or_else(|| TraceError::Recorder(format!("round {round} was never requested")))
    }

    /// Ends the task after `total_actions` executed actions and validates it. Rounds whose reply
    /// never came (the task ended first) are dropped; a received chunk with no `ChunkDone` counts
    /// as not executed.
    pub fn finish(self, total_actions: u32) -> Result<TaskTrace, TraceError> {
        let rounds = self
            .rounds
            .into_iter()
            .filter_map(|r| {
                let (horizon, received, inference, confidence) = r.reply?;
                Some(RoundTrace {
                    issued_at_action: r.issued_at_action,
                    aligned_at_action: r.aligned_at_action,
                    horizon,
                    executed: r.executed.unwrap_or(0),
                    gen_latency_us: inference,
                    round_trip_us: Some(received.saturating_sub(r.sent_at_us)),
                    obs_bytes: r.obs_bytes,
                    confidence,
                })
            })
            .collect();
        let meta = self.meta;
        let trace = TaskTrace {
            task: meta.task,
            label: meta.label,
            setting: meta.setting,
            horizon: meta.horizon,
            control_hz: meta.control_hz,
            chunk_len: meta.chunk_len,
            total_actions,
            rounds,
        };
        trace.validate()?;
        Ok(trace)
    }
}

/// Records tasks one after another into a trace file: [`TraceRecorder::begin_task`], the task's
/// [`RoundEvent`]s, [`TraceRecorder::end_task`] (which writes its line), and so on.
pub struct TraceRecorder<W: Write> {
    writer: TraceWriter<W>,
    task: Option<TaskRecording>,
}

impl<W: Write> TraceRecorder<W> {
    /// Starts a trace file with a `recorded` header.
    pub fn new(out: W) -> Result<Self, TraceError> {
        Ok(TraceRecorder {
            writer: TraceWriter::new(out, &TraceHeader::new(TraceSource::Recorded))?,
            task: None,
        })
    }

    /// Begins recording a task. A task still open is an error: end it first.
    pub fn begin_task(&mut self, meta: TaskMeta) -> Result<(), TraceError> {
        if let Some(open) = &self.task {
            return Err(TraceError::Recorder(format!(
                "task {} is still open",
                open.meta.task
            )));
        }
        self.task = Some(TaskRecording::new(meta));
        Ok(())
    }

    /// Feeds one event of the open task.
    pub fn record(&mut self, event: RoundEvent) -> Result<(), TraceError> {
        match &mut self.task {
            Some(t) => t.record(event),
            None => Err(TraceError::Recorder("event before begin_task".into())),
        }
    }

    /// Ends the open task (see [`TaskRecording::finish`]) and writes its line.
    pub fn end_task(&mut self, total_actions: u32) -> Result<TaskTrace, TraceError> {
        let task = self
            .task
            .take()
            .ok_or_else(|| TraceError::Recorder("end_task without begin_task".into()))?;
        let trace = task.finish(total_actions)?;
        self.writer.write_task(&trace)?;
        Ok(trace)
    }

    /// Flushes and returns the writer. An open task is discarded.
    pub fn finish(self) -> Result<W, TraceError> {
        self.writer.finish()
    }
}

/// What a [`RunnerTraceRecorder`] writes into every task it records.
#[derive(Clone, Debug, PartialEq)]
pub struct RecordSetup {
    /// Setting label (`static`, `dynamic`, ...) of every recorded task.
    pub setting: String,
    /// The horizon policy the robot requested.
    pub horizon: HorizonSetting,
    /// Control frequency of the robot.
    pub control_hz: f32,
    /// Bytes of one observation as the robot sends it (the runner's events do not carry it).
    pub obs_bytes: u32,
}

#[derive(Debug)]
struct RunnerTask {
    recording: TaskRecording,
    /// Σ actions executed by chunks that ended.
    executed_before: u64,
    /// The chunk now executing: (round, executable actions).
    current: Option<(u64, u32)>,
    /// Actions counted per ended chunk; a repeated report of the same chunk replaces the
    /// earlier count rather than adding to it.
    ended: BTreeMap<u64, u32>,
}

/// Records the [`RunnerEvent`](crate::robot::RunnerEvent)s of `RobotRunner`s (one or many
/// tasks, interleaved) into a trace file, one line per finished task: what `kairos robot
/// --record FILE` does.
///
/// The runner's events carry everything a trace needs but the action index at which each
/// request went out; it is reconstructed as the actions of the chunks that already ended plus
/// those of the current chunk that had started when the request was sent (its executable
/// actions, `horizon − discarded`, minus the Last Exec Info's `actions_remaining`).
pub struct RunnerTraceRecorder<W: Write> {
    writer: TraceWriter<W>,
    setup: RecordSetup,
    tasks: BTreeMap<u64, RunnerTask>,
    written: usize,
}

impl<W: Write> RunnerTraceRecorder<W> {
    /// Starts a trace file with a `recorded` header.
    pub fn new(out: W, setup: RecordSetup) -> Result<Self, TraceError> {
        Ok(RunnerTraceRecorder {
            writer: TraceWriter::new(out, &TraceHeader::new(TraceSource::Recorded))?,
            setup,
            tasks: BTreeMap::new(),
            written: 0,
        })
    }

    /// Tasks written so far.
    pub fn tasks_written(&self) -> usize {
        self.written
    }

    /// Feeds one runner event.
    pub fn on_event(&mut self, event: &crate::robot::RunnerEvent) -> Result<(), TraceError> {
        use crate::robot::RunnerEvent as E;
        match event {
            E::RequestSent {
                task,
                round,
                at_us,
                last_exec,
            } => {
                let setup = &self.setup;
                let t = self.tasks.entry(*task).or_insert_with(|| RunnerTask {
                    recording: TaskRecording::new(TaskMeta {
                        task: *task,
                        label: None,
                        setting: setup.setting.clone(),
                        horizon: setup.horizon.clone(),
                        control_hz: setup.control_hz,
                        chunk_len: 0,
                    }),
                    executed_before: 0,
                    current: None,
                    ended: BTreeMap::new(),
                });
                let in_current = match (t.current, last_exec) {
                    (Some((_, executable)), Some(info)) => {
                        u64::from(executable.saturating_sub(info.actions_remaining))
                    }
                    _ => 0,
                };
                let at_action = u32::try_from(t.executed_before + in_current).unwrap_or(u32::MAX);
                t.recording.record(RoundEvent::Requested {
                    round: *round,
                    at_action,
                    sent_at_us: *at_us,
                    obs_bytes: self.setup.obs_bytes,
                })?;
            }
            E::ReplyReceived { task, record } => {
                let t = self.task(*task)?;
                if t.recording.meta.chunk_len == 0 {
                    t.recording.meta.chunk_len = record.chunk_len;
                }
                t.recording.record(RoundEvent::Replied {
                    round: record.round,
                    received_at_us: record.received_at_us,
                    horizon: record.horizon,
                    inference_us: record.timing.inference_us,
                    confidence: None,
                })?;
                let executable = record.horizon.saturating_sub(record.discarded);
                if executable > 0 {
                    t.current = Some((record.round, executable));
                }
            }
            E::ChunkEnded {
                task,
                round,
                executed,
                ..
            } => {
                let t = self.task(*task)?;
                t.recording.record(RoundEvent::ChunkDone {
                    round: *round,
                    executed: *executed,
                })?;
                let counted = t.ended.insert(*round, *executed).unwrap_or(0);
                t.executed_before = t.executed_before - u64::from(counted) + u64::from(*executed);
                if t.current.is_some_and(|(r, _)| r == *round) {
                    t.current = None;
                }
            }
            E::TaskFinished(summary) => {
                let t = self.tasks.remove(&summary.task).ok_or_else(|| {
                    TraceError::Recorder(format!("task {} finished unseen", summary.task))
                })?;
                let total = u32::try_from(summary.actions_executed).unwrap_or(u32::MAX);
                let trace = t.recording.finish(total)?;
                self.writer.write_task(&trace)?;
                self.written += 1;
            }
            E::ObservationRefetched {
                task,
                round,
                actions_executed,
                ..
            } => {
                let t = self.task(*task)?;
                t.recording.record(RoundEvent::Refetched {
                    round: *round,
                    at_action: u32::try_from(*actions_executed).unwrap_or(u32::MAX),
                })?;
            }
            E::RoundFailed { .. } | E::Idle { .. } => {}
        }
        Ok(())
    }

    fn task(&mut self, task: u64) -> Result<&mut RunnerTask, TraceError> {
        self.tasks.get_mut(&task).ok_or_else(|| {
            TraceError::Recorder(format!("event of task {task} before its first request"))
        })
    }

    /// Flushes and returns the writer; tasks that never finished are not written.
    pub fn finish(self) -> Result<W, TraceError> {
        self.writer.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round(at: u32, h: u32, executed: u32) -> RoundTrace {
        RoundTrace {
            issued_at_action: at,
            aligned_at_action: None,
            horizon: h,
            executed,
            gen_latency_us: 40_000,
            round_trip_us: Some(43_000),
            obs_bytes: 60_000,
            confidence: None,
        }
    }

    fn task() -> TaskTrace {
        TaskTrace {
            task: 7,
            label: Some("libero_spatial/0".into()),
            setting: "static".into(),
            horizon: HorizonSetting {
                policy: "static".into(),
                params: BTreeMap::from([("h".to_string(), 10.0)]),
            },
            control_hz: 30.0,
            chunk_len: 50,
            total_actions: 25,
            rounds: vec![
                round(0, 10, 6),
                round(5, 10, 5),
                round(10, 10, 5),
                round(15, 10, 9),
            ],
        }
    }

    #[test]
    fn round_trip_preserves_every_field() {
        let mut t = task();
        t.rounds[1].confidence = Some((0..50).map(|i| 0.5 + i as f32 * 0.01).collect());
        let set = TraceSet {
            header: TraceHeader::new(TraceSource::Generated),
            tasks: vec![t],
        };
        let bytes = set.write(Vec::new()).unwrap();
        let back = TraceSet::read(bytes.as_slice()).unwrap();
        assert_eq!(back, set);
        assert_eq!(back.settings(), vec!["static".to_string()]);
    }

    #[test]
    fn validation_rejects_impossible_tasks() {
        let mut t = task();
        t.rounds[2].issued_at_action = 30; // beyond what rounds 0 and 1 reach (15)
        assert!(matches!(t.validate(), Err(TraceError::Invalid { .. })));

        let mut t = task();
        t.total_actions = 26; // last chunk reaches 25
        let err = t.validate().unwrap_err().to_string();
        assert!(err.contains("short of total_actions"), "{err}");

        let mut t = task();
        t.rounds[0].issued_at_action = 1;
        assert!(t.validate().is_err());

        let mut t = task();
        t.rounds[1].horizon = 51;
        assert!(t.validate().is_err());

        let mut t = task();
        t.rounds[1].confidence = Some(vec![1.0; 49]);
        assert!(t.validate().is_err());

        let mut t = task();
        t.control_hz = 0.0;
        assert!(t.validate().is_err());
    }

    #[test]
    fn reader_rejects_other_versions_and_formats() {
        let mut header = TraceHeader::new(TraceSource::Recorded);
        header.version = 2;
        let text = serde_json::to_string(&header).unwrap();
        let err = TraceSet::read(text.as_bytes()).unwrap_err();
        assert!(matches!(err, TraceError::Unsupported(_)), "{err}");

        let err = TraceSet::read("{\"format\":\"x\"}".as_bytes()).unwrap_err();
        assert!(matches!(err, TraceError::Parse { line: 1, .. }), "{err}");

        let err = TraceSet::read("".as_bytes()).unwrap_err();
        assert!(matches!(err, TraceError::Unsupported(_)));
    }

    #[test]
    fn recorder_pairs_overlapping_rounds_in_order() {
        let mut rec = TraceRecorder::new(Vec::new()).unwrap();
        rec.begin_task(TaskMeta {
            task: 1,
            label: None,
            setting: "dynamic".into(),
            horizon: HorizonSetting {
                policy: "threshold".into(),
                params: BTreeMap::new(),
            },
            control_hz: 10.0,
            chunk_len: 8,
        })
        .unwrap();
        rec.record(RoundEvent::Requested {
            round: 0,
            at_action: 0,
            sent_at_us: 0,
            obs_bytes: 100,
        })
        .unwrap();
        rec.record(RoundEvent::Replied {
            round: 0,
            received_at_us: 50_000,
            horizon: 6,
            inference_us: 40_000,
            confidence: None,
        })
        .unwrap();
        // Next request goes out while chunk 0 still runs.
        rec.record(RoundEvent::Requested {
            round: 1,
            at_action: 3,
            sent_at_us: 350_000,
            obs_bytes: 100,
        })
        .unwrap();
        rec.record(RoundEvent::Replied {
            round: 1,
            received_at_us: 400_000,
            horizon: 8,
            inference_us: 40_000,
            confidence: None,
        })
        .unwrap();
        rec.record(RoundEvent::ChunkDone {
            round: 0,
            executed: 4,
        })
        .unwrap();
        rec.record(RoundEvent::ChunkDone {
            round: 1,
            executed: 7,
        })
        .unwrap();
        let t = rec.end_task(11).unwrap();
        assert_eq!(t.rounds.len(), 2);
        assert_eq!(t.rounds[0].executed, 4);
        assert_eq!(t.rounds[1].issued_at_action, 3);
        assert_eq!(t.rounds[1].executed, 7);
        assert_eq!(t.rounds[1].round_trip_us, Some(50_000));
        let bytes = rec.finish().unwrap();
        let set = TraceSet::read(bytes.as_slice()).unwrap();
        assert_eq!(set.tasks, vec![t]);
        assert_eq!(set.header.source, TraceSource::Recorded);
    }

    #[test]
    fn recorder_refuses_events_out_of_order() {
        let mut rec = TraceRecorder::new(Vec::new()).unwrap();
        assert!(
            rec.record(RoundEvent::ChunkDone {
                round: 0,
                executed: 1
            })
            .is_err()
        );
        rec.begin_task(TaskMeta {
            task: 1,
            label: None,
            setting: "static".into(),
            horizon: HorizonSetting {
                policy: "static".into(),
                params: BTreeMap::new(),
            },
            control_hz: 10.0,
            chunk_len: 8,
        })
        .unwrap();
        assert!(
            rec.record(RoundEvent::Replied {
                round: 0,
                received_at_us: 1,
                horizon: 2,
                inference_us: 1,
                confidence: None
            })
            .is_err()
        );
        let requested = |round| RoundEvent::Requested {
            round,
            at_action: 0,
            sent_at_us: 0,
            obs_bytes: 1,
        };
        rec.record(requested(3)).unwrap();
        assert!(rec.record(requested(3)).is_err(), "round ids must increase");
        assert!(
            rec.record(RoundEvent::ChunkDone {
                round: 3,
                executed: 1
            })
            .is_err(),
            "a chunk cannot be done before it arrived"
        );
    }

    #[test]
    fn runner_events_become_a_trace_with_reconstructed_action_indices() {
        use crate::protocol::messages::{LastExecInfo, Timing};
        use crate::robot::{RoundRecord, RunnerEvent, TaskSummary};

        let setup = RecordSetup {
            setting: "static".into(),
            horizon: HorizonSetting {
                policy: "static".into(),
                params: BTreeMap::from([("h".to_string(), 8.0)]),
            },
            control_hz: 10.0,
            obs_bytes: 1234,
        };
        let reply = |round, received_at_us, discarded| RunnerEvent::ReplyReceived {
            task: 7,
            record: RoundRecord {
                round,
                sent_at_us: 0,
                received_at_us,
                attempts: 1,
                refetches: 0,
                horizon: 8,
                chunk_len: 50,
                discarded,
                executed: 0,
                policy: "static".into(),
                timing: Timing {
                    inference_us: 40_000,
                    ..Timing::default()
                },
            },
        };
        let sent = |round, at_us, remaining: Option<u32>| RunnerEvent::RequestSent {
            task: 7,
            round,
            at_us,
            last_exec: remaining.map(|actions_remaining| LastExecInfo {
                exec_started_at_us: 0,
                actions_remaining,
                control_hz: 10.0,
                round: None,
                delay: None,
            }),
        };
        let ended = |round, executed| RunnerEvent::ChunkEnded {
            task: 7,
            round,
            executed,
            dropped: 0,
        };
        // Chunks of 8 at 10 Hz, the next request after half of a chunk's executable actions:
        // round 1 after 4 of chunk 0 (index 4); chunk 1 arrives with one action discarded (7
        // executable) after chunk 0 ran 5; round 2 after 4 of chunk 1 (index 5 + 4 = 9).
        let events = [
            sent(0, 0, None),
            reply(0, 50_000, 0),
            sent(1, 350_000, Some(4)),
            ended(0, 5),
            reply(1, 400_000, 1),
            // The runner may report an ended chunk twice (ran out, then replaced): count it once.
            ended(0, 5),
            sent(2, 800_000, Some(3)),
            ended(1, 5),
            reply(2, 850_000, 1),
            ended(2, 7),
            RunnerEvent::TaskFinished(TaskSummary {
                task: 7,
                rounds: Vec::new(),
                started_at_us: 0,
                finished_at_us: 1_500_000,
                actions_executed: 17,
                idle_us: 50_000,
                failed_rounds: 0,
                server_record: None,
                end_error: None,
            }),
        ];
        let mut rec = RunnerTraceRecorder::new(Vec::new(), setup).unwrap();
        for e in &events {
            rec.on_event(e).unwrap();
        }
        assert_eq!(rec.tasks_written(), 1);
        let set = TraceSet::read(rec.finish().unwrap().as_slice()).unwrap();
        let t = &set.tasks[0];
        assert_eq!((t.task, t.chunk_len, t.total_actions), (7, 50, 17));
        let got: Vec<(u32, u32, u32)> = t
            .rounds
            .iter()
            .map(|r| (r.issued_at_action, r.horizon, r.executed))
            .collect();
        assert_eq!(got, vec![(0, 8, 5), (4, 8, 5), (9, 8, 7)]);
        assert_eq!(t.rounds[1].round_trip_us, Some(50_000));
        assert_eq!(t.rounds[2].obs_bytes, 1234);
    }

    #[test]
    fn a_refetched_round_is_aligned_at_the_fresh_observation() {
        use crate::protocol::messages::{LastExecInfo, Timing};
        use crate::robot::{RoundRecord, RunnerEvent, TaskSummary};

        let setup = RecordSetup {
            setting: "static".into(),
            horizon: HorizonSetting {
                policy: "static".into(),
                params: BTreeMap::from([("h".to_string(), 8.0)]),
            },
            control_hz: 10.0,
            obs_bytes: 10,
        };
        let reply = |round, discarded| RunnerEvent::ReplyReceived {
            task: 1,
            record: RoundRecord {
                round,
                sent_at_us: 0,
                received_at_us: 0,
                attempts: 1,
                refetches: 0,
                horizon: 8,
                chunk_len: 8,
                discarded,
                executed: 0,
                policy: "static".into(),
                timing: Timing::default(),
            },
        };
        // Round 1 goes out after 4 actions of chunk 0, queues, and the server re-fetches the
        // observation after 6. Chunk 1 arrives after 7: one action discarded, 7 executed, so the
        // task reaches action 6 + 8 = 14. Aligned at the request (4) the chunks would only cover
        // 12 < 14 and the trace would be rejected as inconsistent.
        let events = [
            RunnerEvent::RequestSent {
                task: 1,
                round: 0,
                at_us: 0,
                last_exec: None,
            },
            reply(0, 0),
            RunnerEvent::RequestSent {
                task: 1,
                round: 1,
                at_us: 400_000,
                last_exec: Some(LastExecInfo {
                    exec_started_at_us: 0,
                    actions_remaining: 4,
                    control_hz: 10.0,
                    round: None,
                    delay: None,
                }),
            },
            RunnerEvent::ObservationRefetched {
                task: 1,
                round: 1,
                at_us: 600_000,
                actions_executed: 6,
            },
            RunnerEvent::ChunkEnded {
                task: 1,
                round: 0,
                executed: 7,
                dropped: 1,
            },
            reply(1, 1),
            RunnerEvent::ChunkEnded {
                task: 1,
                round: 1,
                executed: 7,
                dropped: 0,
            },
            RunnerEvent::TaskFinished(TaskSummary {
                task: 1,
                rounds: Vec::new(),
                started_at_us: 0,
                finished_at_us: 1_400_000,
                actions_executed: 14,
                idle_us: 0,
                failed_rounds: 0,
                server_record: None,
                end_error: None,
            }),
        ];
        let mut rec = RunnerTraceRecorder::new(Vec::new(), setup).unwrap();
        for e in &events {
            rec.on_event(e).unwrap();
        }
        assert_eq!(rec.tasks_written(), 1);
        let set = TraceSet::read(rec.finish().unwrap().as_slice()).unwrap();
        let r = &set.tasks[0].rounds[1];
        assert_eq!(
            (r.issued_at_action, r.aligned_at_action, r.executed),
            (4, Some(6), 7)
        );
    }

    #[test]
    fn alignment_before_the_request_is_invalid() {
        let mut t = task();
        t.rounds[1].aligned_at_action = Some(5);
        t.validate().unwrap();
        t.validate().unwrap();
        t.rounds[1].aligned_at_action = Some(3);
        assert!(t.validate().is_err());
    }
}
