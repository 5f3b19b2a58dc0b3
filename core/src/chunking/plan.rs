//! One round's chunking plan: its model input and how its chunk goes into the reply.
//!
//! | strategy | model input | reply |
//! |---|---|---|
//! | `skip` | the observation | the chunk; the robot skips the first `start` actions |
//! | `from_start` | the observation | the `start` committed actions, then the chunk from its first action |
//! | `arrival_state` | the state on arrival (forecast, or rolled forward) | as `from_start` |
//! | `rtc`, `rtc_vjp` | guidance toward the previous chunk | the chunk |
//! | `inpaint` | the committed actions as a hard prefix | the chunk |
//! | `ensemble` | the observation | the overlap blended 0.3 × previous + 0.7 × new |
//!
//! The committed actions are the previous chunk the robot executes from the capture on: the
//! task's last reply, from the position its Last Exec Info gives (`H − actions_remaining`).
//! `from_start` and `arrival_state` plan a chunk whose first action belongs to the arrival, so
//! the reply puts the committed actions in front of it (and drops as many from its end, so it
//! keeps `N` actions at most): action `i` of every reply belongs to `i` steps after the capture.

use kairos_engine_types::{ActionSpace, Guidance, GuidanceMode};
use kairos_protocol::{ChunkingStrategy, DType, Reply, Tensor};

use super::{DelayPrediction, ENSEMBLE_OLD_WEIGHT, RoundChunking};

/// The chunk the robot executes while the round is in flight, as the server answered it.
#[derive(Clone, Copy, Debug)]
pub struct PreviousChunk<'a> {
    /// The reply's actions, `[H][action_dim]`.
    pub actions: &'a [f32],
    /// Values per action.
    pub action_dim: usize,
}

/// How one round is answered (kept from the start of its batch to its reply).
#[derive(Clone, Debug, PartialEq)]
pub struct RoundPlan {
    /// The strategy the round asked for.
    pub requested: ChunkingStrategy,
    /// The strategy applied: `requested`, or `skip` when what it needs was missing.
    pub applied: ChunkingStrategy,
    /// The predicted `d`.
    pub prediction: DelayPrediction,
    /// The previous chunk from the capture on, `[L][action_dim]` (empty when the robot had
    /// none, or when it was not known).
    pub leftover: Vec<f32>,
    /// Values per action.
    pub action_dim: usize,
}

/// What the engine runs for the round, beside the observation.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlannedInput {
    /// The state to plan from instead of the observed one.
    pub state: Option<Vec<f32>>,
    /// Guidance toward the committed actions.
    pub guidance: Option<Guidance>,
}

/// Plans one round: `chunking` as resolved, the predicted `d`, the task's last reply (if it is
/// the chunk the robot executes), the observed `state`, and the model's action space.
pub fn plan_round(
    chunking: &RoundChunking,
    prediction: DelayPrediction,
    previous: Option<PreviousChunk<'_>>,
    state: &[f32],
    action_space: &ActionSpace,
    action_dim: usize,
) -> (RoundPlan, PlannedInput) {
    let remaining = prediction.remaining_at_capture as usize;
    // The previous chunk from the capture on: the last `remaining` actions of the last reply.
    let leftover: Option<Vec<f32>> = if remaining == 0 {
        Some(Vec::new())
    } else {
        previous.and_then(|p| {
            let rows = p.actions.len() / p.action_dim.max(1);
            (p.action_dim == action_dim && rows >= remaining)
                .then(|| p.actions[(rows - remaining) * action_dim..].to_vec())
        })
    };
    let requested = chunking.strategy;
    let Some(leftover) = leftover else {
        // The robot executes a chunk the server does not know: nothing to plan around.
        return (
            RoundPlan {
                requested,
                applied: ChunkingStrategy::Skip,
                prediction,
                leftover: Vec::new(),
                action_dim,
            },
            PlannedInput::default(),
        );
    };
    let start = prediction.start as usize;
    let committed = &leftover[..start.min(remaining) * action_dim];
    let mut input = PlannedInput::default();
    let mut applied = requested;
    match requested {
        ChunkingStrategy::Skip | ChunkingStrategy::FromStart | ChunkingStrategy::Ensemble => {}
        ChunkingStrategy::ArrivalState => {
            input.state = match &chunking.forecast {
                Some(rows) if start > 0 => rows.get(start.min(rows.len()) - 1).cloned(),
                Some(_) => None,
                None => action_space.roll_forward(state, committed, action_dim),
            };
            if start > 0 && input.state.is_none() {
                // Validation refuses this strategy where it cannot apply; a forecast of the
                // wrong length is the one way here.
                applied = ChunkingStrategy::Skip;
            }
        }
        ChunkingStrategy::Rtc | ChunkingStrategy::RtcVjp | ChunkingStrategy::Inpaint => {
            if !leftover.is_empty() {
                input.guidance = Some(Guidance {
                    mode: match requested {
                        ChunkingStrategy::Rtc => GuidanceMode::Rtc,
                        ChunkingStrategy::RtcVjp => GuidanceMode::RtcVjp,
                        _ => GuidanceMode::Inpaint,
                    },
                    prefix: leftover.clone(),
                    delay: start,
                    execution_horizon: chunking.execution_horizon as usize,
                    schedule: chunking.schedule,
                    max_guidance_weight: chunking.max_guidance_weight,
                });
            }
        }
    }
    (
        RoundPlan {
            requested,
            applied,
            prediction,
            leftover,
            action_dim,
        },
        input,
    )
}

impl RoundPlan {
    /// Actions the robot executes before the chunk arrives (the reply's `start`).
    pub fn start(&self) -> usize {
        let rows = self.leftover.len() / self.action_dim.max(1);
        (self.prediction.start as usize).min(rows)
    }

    /// Puts the round's chunk into `reply` as its strategy says (module docs), and fills the
    /// reply's `start`, `delay` and `chunking`.
    pub fn finish(&self, reply: &mut Reply) {
        let d = self.action_dim;
        let start = self.start();
        if d > 0 && reply.actions.shape.get(1).is_some_and(|&w| w as usize == d) {
            let mut actions = f32_values(&reply.actions.data);
            match self.applied {
                ChunkingStrategy::FromStart | ChunkingStrategy::ArrivalState if start > 0 => {
                    let keep = (reply.horizon as usize)
                        .min((reply.chunk_len as usize).saturating_sub(start));
                    let mut shifted = self.leftover[..start * d].to_vec();
                    shifted.extend_from_slice(&actions[..keep * d]);
                    actions = shifted;
                }
                ChunkingStrategy::Ensemble => {
                    for (new, old) in actions.iter_mut().zip(&self.leftover) {
                        *new = ENSEMBLE_OLD_WEIGHT * old + (1.0 - ENSEMBLE_OLD_WEIGHT) * *new;
                    }
                }
                _ => {}
            }
            let rows = actions.len() / d;
            reply.horizon = u32::try_from(rows).unwrap_or(u32::MAX);
            reply.actions = Tensor {
                dtype: DType::F32,
                shape: vec![reply.horizon, u32::try_from(d).unwrap_or(u32::MAX)],
                data: actions.iter().flat_map(|v| v.to_le_bytes()).collect(),
            };
        }
        reply.start = Some(u32::try_from(start).unwrap_or(u32::MAX));
        reply.delay = Some(self.prediction.delay);
        reply.chunking = Some(self.applied.as_str().to_string());
    }
}

/// Little-endian f32 values of a tensor's bytes.
fn f32_values(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chunking::ChunkingDefaults;
    use crate::time::Timestamp;

    fn prediction(delay: u32, start: u32, remaining: u32) -> DelayPrediction {
        DelayPrediction {
            arrival: Timestamp::from_micros(1),
            delay,
            start,
            remaining_at_capture: remaining,
        }
    }

    fn chunking(strategy: ChunkingStrategy) -> RoundChunking {
        RoundChunking::with_defaults(strategy, &ChunkingDefaults::default())
    }

    fn reply(values: &[f32], chunk_len: u32) -> Reply {
        let rows = (values.len() / 2) as u32;
        Reply {
            task: 1,
            round: 2,
            horizon: rows,
            chunk_len,
            actions: Tensor::from_f32(vec![rows, 2], values).unwrap(),
            policy: "static".into(),
            timing: Default::default(),
            start: None,
            delay: None,
            chunking: None,
        }
    }

    // The previous reply: 4 actions of 2 values; the robot has the last 3 left at the capture.
    const PREVIOUS: [f32; 8] = [0.0, 0.0, 1.0, 10.0, 2.0, 20.0, 3.0, 30.0];

    fn previous() -> Option<PreviousChunk<'static>> {
        Some(PreviousChunk {
            actions: &PREVIOUS,
            action_dim: 2,
        })
    }

    #[test]
    fn rtc_and_inpaint_guide_toward_the_previous_chunk_from_the_capture() {
        for (strategy, mode) in [
            (ChunkingStrategy::Rtc, GuidanceMode::Rtc),
            (ChunkingStrategy::RtcVjp, GuidanceMode::RtcVjp),
            (ChunkingStrategy::Inpaint, GuidanceMode::Inpaint),
        ] {
            let (plan, input) = plan_round(
                &chunking(strategy),
                prediction(2, 2, 3),
                previous(),
                &[0.0; 2],
                &ActionSpace::Unspecified,
                2,
            );
            let g = input.guidance.unwrap();
            assert_eq!((g.mode, g.delay), (mode, 2));
            assert_eq!(g.prefix, PREVIOUS[2..]);
            assert_eq!(g.execution_horizon, 10);
            assert_eq!(plan.applied, strategy);
            let mut r = reply(&[5.0; 8], 50);
            plan.finish(&mut r);
            assert_eq!((r.start, r.delay), (Some(2), Some(2)));
            assert_eq!(r.chunking.as_deref(), Some(strategy.as_str()));
            assert_eq!(r.actions.to_f32().unwrap(), [5.0; 8]);
        }
    }

    #[test]
    fn arrival_indexed_strategies_put_the_committed_actions_first() {
        let space = ActionSpace::AbsolutePosition {
            state_index: vec![Some(1), None],
        };
        let (plan, input) = plan_round(
            &chunking(ChunkingStrategy::ArrivalState),
            prediction(2, 2, 3),
            previous(),
            &[7.0, 7.0, 7.0],
            &space,
            2,
        );
        // Rolled forward through the two committed actions (1, 10), (2, 20): state[1] = 2.
        assert_eq!(input.state, Some(vec![7.0, 2.0, 7.0]));
        assert!(input.guidance.is_none());
        let mut r = reply(&[5.0, 5.0, 6.0, 6.0, 8.0, 8.0], 4);
        plan.finish(&mut r);
        // 2 committed + the chunk's first 2 (chunk_len 4 caps the reply).
        assert_eq!(r.horizon, 4);
        assert_eq!(
            r.actions.to_f32().unwrap(),
            [1.0, 10.0, 2.0, 20.0, 5.0, 5.0, 6.0, 6.0]
        );
        assert_eq!(r.start, Some(2));
        // A client forecast wins, row d - 1.
        let forecast = RoundChunking {
            forecast: Some(vec![vec![1.0; 3], vec![2.0; 3], vec![3.0; 3]]),
            ..chunking(ChunkingStrategy::ArrivalState)
        };
        let (_, input) = plan_round(
            &forecast,
            prediction(2, 2, 3),
            previous(),
            &[7.0; 3],
            &ActionSpace::Unspecified,
            2,
        );
        assert_eq!(input.state, Some(vec![2.0; 3]));
        // from_start: the observation as is, the same reply layout.
        let (plan, input) = plan_round(
            &chunking(ChunkingStrategy::FromStart),
            prediction(1, 1, 3),
            previous(),
            &[7.0; 3],
            &ActionSpace::Unspecified,
            2,
        );
        assert_eq!(input, PlannedInput::default());
        let mut r = reply(&[5.0; 4], 50);
        plan.finish(&mut r);
        assert_eq!(r.actions.to_f32().unwrap(), [1.0, 10.0, 5.0, 5.0, 5.0, 5.0]);
    }

    #[test]
    fn ensemble_blends_the_overlap_and_skip_leaves_the_chunk() {
        let (plan, _) = plan_round(
            &chunking(ChunkingStrategy::Ensemble),
            prediction(1, 1, 3),
            previous(),
            &[0.0; 2],
            &ActionSpace::Unspecified,
            2,
        );
        let mut r = reply(&[10.0; 10], 50);
        plan.finish(&mut r);
        let got = r.actions.to_f32().unwrap();
        assert_eq!(got[0], 0.3 * 1.0 + 0.7 * 10.0);
        assert_eq!(got[5], 0.3 * 30.0 + 0.7 * 10.0);
        assert_eq!(&got[6..], &[10.0; 4]);
        let (plan, input) = plan_round(
            &chunking(ChunkingStrategy::Skip),
            prediction(5, 3, 3),
            previous(),
            &[0.0; 2],
            &ActionSpace::Unspecified,
            2,
        );
        assert_eq!(input, PlannedInput::default());
        let mut r = reply(&[10.0; 10], 50);
        plan.finish(&mut r);
        assert_eq!((r.start, r.delay), (Some(3), Some(5)));
        assert_eq!(r.actions.to_f32().unwrap(), [10.0; 10]);
    }

    #[test]
    fn an_unknown_previous_chunk_falls_back_to_skip_and_an_idle_robot_needs_none() {
        let (plan, input) = plan_round(
            &chunking(ChunkingStrategy::Rtc),
            prediction(2, 2, 3),
            None,
            &[0.0; 2],
            &ActionSpace::Unspecified,
            2,
        );
        assert_eq!(plan.applied, ChunkingStrategy::Skip);
        assert_eq!(input, PlannedInput::default());
        // A reply shorter than what the robot says it has left is not the chunk it executes.
        let short = PreviousChunk {
            actions: &PREVIOUS[..4],
            action_dim: 2,
        };
        let (plan, _) = plan_round(
            &chunking(ChunkingStrategy::Rtc),
            prediction(2, 2, 3),
            Some(short),
            &[0.0; 2],
            &ActionSpace::Unspecified,
            2,
        );
        assert_eq!(plan.applied, ChunkingStrategy::Skip);
        // Idle robot (first round): nothing committed, the strategy applies as is.
        let (plan, input) = plan_round(
            &chunking(ChunkingStrategy::Rtc),
            prediction(3, 0, 0),
            None,
            &[0.0; 2],
            &ActionSpace::Unspecified,
            2,
        );
        assert_eq!((plan.applied, plan.start()), (ChunkingStrategy::Rtc, 0));
        assert!(input.guidance.is_none());
    }
}
