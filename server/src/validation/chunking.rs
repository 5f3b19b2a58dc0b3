//! `Submit.chunking` → the round's [`RoundChunking`], checked against what the served model
//! can do: a strategy that cannot apply is refused with `invalid_request` before the round is
//! queued, saying why and what would work instead.

use kairos_core::chunking::{ChunkingDefaults, RoundChunking, engine_schedule};
use kairos_engine::{ActionSpace, GuidanceMode, GuidanceSupport};
use kairos_sdk::protocol::{ChunkingSelection, ChunkingStrategy};

use super::RequestError;

/// What the server's chunking strategies may do for the served model.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ChunkingRules {
    /// `[chunking]`: the default strategy and the real-time chunking settings.
    pub defaults: ChunkingDefaults,
    /// Which guidance the model's sampler applies on its backend.
    pub guidance: GuidanceSupport,
    /// What the model's actions are (whether the server can roll a state forward).
    pub action_space: ActionSpace,
}

fn invalid(field: &str, reason: String) -> RequestError {
    RequestError::Invalid {
        field: field.into(),
        reason,
    }
}

impl ChunkingRules {
    /// Why `strategy` cannot apply to the model without a client forecast, if it cannot.
    pub fn refusal(&self, strategy: ChunkingStrategy, model: &str) -> Option<String> {
        let mode = match strategy {
            ChunkingStrategy::Rtc => GuidanceMode::Rtc,
            ChunkingStrategy::RtcVjp => GuidanceMode::RtcVjp,
            ChunkingStrategy::Inpaint => GuidanceMode::Inpaint,
            ChunkingStrategy::ArrivalState => {
                return (self.action_space == ActionSpace::Unspecified).then(|| {
                    format!(
                        "`arrival_state` needs the state the robot will have on arrival: model \
                         `{model}` does not say its actions are absolute position targets, so \
                         the server cannot roll the state forward; send `chunking.forecast` (the \
                         robot's own forecast after each of its next actions)"
                    )
                });
            }
            ChunkingStrategy::Skip | ChunkingStrategy::FromStart | ChunkingStrategy::Ensemble => {
                return None;
            }
        };
        if self.guidance.supports(mode) {
            return None;
        }
        Some(if mode == GuidanceMode::RtcVjp && self.guidance.prefix {
            format!(
                "`rtc_vjp` needs a backward pass through model `{model}`'s velocity network, \
                 which its backend (the fast CPU kernels) does not have; use `rtc` (LeRobot's \
                 guidance, no backward pass) or serve the model on the Candle path \
                 (`kernels = \"candle\"`)"
            )
        } else {
            format!(
                "model `{model}` does not sample with the shared flow sampler, so it cannot \
                 apply `{}` guidance; use `skip`, `from_start`, `ensemble` or `arrival_state`",
                strategy.as_str()
            )
        })
    }

    /// The round's chunking: the client's selection (or the default) with the server's
    /// settings where it sets none, checked against the model (`state_dim` for a forecast).
    /// `committed`: whether the robot executes actions while the round is in flight (its Last
    /// Exec Info has some left); without, every strategy applies trivially.
    pub fn resolve(
        &self,
        selection: Option<ChunkingSelection>,
        model: &str,
        state_dim: usize,
        committed: bool,
    ) -> Result<RoundChunking, RequestError> {
        let Some(selection) = selection else {
            // The default applies where it can: `arrival_state` without a way to roll the
            // state forward falls back to `skip` when the round is planned (and is counted as
            // such); launch refuses a default guidance the model cannot apply.
            return Ok(RoundChunking::with_defaults(
                self.defaults.strategy,
                &self.defaults,
            ));
        };
        let mut chunking = RoundChunking::with_defaults(selection.strategy, &self.defaults);
        if let Some(schedule) = selection.schedule {
            chunking.schedule = engine_schedule(schedule);
        }
        if let Some(weight) = selection.max_guidance_weight {
            chunking.max_guidance_weight = weight;
        }
        if let Some(horizon) = selection.execution_horizon {
            chunking.execution_horizon = horizon;
        }
        if let Some(forecast) = &selection.forecast {
            let width = forecast.shape.get(1).copied().unwrap_or(0) as usize;
            if width != state_dim {
                return Err(invalid(
                    "chunking.forecast",
                    format!("rows of {width} values, model `{model}` has a state of {state_dim}"),
                ));
            }
            let values = forecast
                .to_f32()
                .map_err(|e| invalid("chunking.forecast", e.to_string()))?;
            chunking.forecast = Some(values.chunks_exact(width).map(<[f32]>::to_vec).collect());
        } else if let Some(reason) = self.refusal(selection.strategy, model)
            && (committed || selection.strategy != ChunkingStrategy::ArrivalState)
        {
            return Err(invalid("chunking.strategy", reason));
        }
        Ok(chunking)
    }
}

#[cfg(test)]
mod tests {
    use kairos_sdk::protocol::{PrefixSchedule, Tensor};

    use super::*;

    fn rules(guidance: GuidanceSupport, action_space: ActionSpace) -> ChunkingRules {
        ChunkingRules {
            defaults: ChunkingDefaults::default(),
            guidance,
            action_space,
        }
    }

    fn refused(rules: &ChunkingRules, selection: ChunkingSelection) -> String {
        match rules.resolve(Some(selection), "m", 3, true) {
            Err(RequestError::Invalid { field, reason }) => format!("{field}: {reason}"),
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    #[test]
    fn a_selection_takes_the_server_settings_it_does_not_set() {
        let r = rules(GuidanceSupport::PREFIX, ActionSpace::Unspecified);
        let none = r.resolve(None, "m", 3, true).unwrap();
        assert_eq!(none.strategy, ChunkingStrategy::ArrivalState, "the default");
        let rtc = r
            .resolve(
                Some(ChunkingSelection {
                    schedule: Some(PrefixSchedule::Exp),
                    execution_horizon: Some(4),
                    ..ChunkingSelection::new(ChunkingStrategy::Rtc)
                }),
                "m",
                3,
                true,
            )
            .unwrap();
        assert_eq!(rtc.strategy, ChunkingStrategy::Rtc);
        assert_eq!(rtc.schedule, kairos_engine::PrefixSchedule::Exp);
        assert_eq!((rtc.execution_horizon, rtc.max_guidance_weight), (4, 10.0));
    }

    #[test]
    fn a_strategy_the_model_cannot_apply_is_refused_with_what_would_work() {
        let fast = rules(GuidanceSupport::PREFIX, ActionSpace::Unspecified);
        let why = refused(&fast, ChunkingSelection::new(ChunkingStrategy::RtcVjp));
        assert!(
            why.starts_with("chunking.strategy") && why.contains("backward pass"),
            "{why}"
        );
        let why = refused(
            &fast,
            ChunkingSelection::new(ChunkingStrategy::ArrivalState),
        );
        assert!(why.contains("chunking.forecast"), "{why}");
        let plain = rules(GuidanceSupport::NONE, ActionSpace::Unspecified);
        let why = refused(&plain, ChunkingSelection::new(ChunkingStrategy::Inpaint));
        assert!(why.contains("`inpaint`"), "{why}");
        // A forecast makes arrival_state possible without an action space; its width must be
        // the model's state.
        let forecast = |width: u32| ChunkingSelection {
            forecast: Some(
                Tensor::from_f32(vec![2, width], &vec![1.0; 2 * width as usize]).unwrap(),
            ),
            ..ChunkingSelection::new(ChunkingStrategy::ArrivalState)
        };
        let ok = fast.resolve(Some(forecast(3)), "m", 3, true).unwrap();
        assert_eq!(ok.forecast, Some(vec![vec![1.0; 3]; 2]));
        assert!(refused(&fast, forecast(2)).contains("state of 3"));
        // With nothing committed (a first round) there is nothing to roll through.
        let first = fast.resolve(
            Some(ChunkingSelection::new(ChunkingStrategy::ArrivalState)),
            "m",
            3,
            false,
        );
        assert_eq!(first.unwrap().strategy, ChunkingStrategy::ArrivalState);
        let absolute = rules(
            GuidanceSupport::ALL,
            ActionSpace::AbsolutePosition {
                state_index: vec![Some(0), Some(1)],
            },
        );
        for strategy in ChunkingStrategy::ALL {
            assert!(
                absolute
                    .resolve(Some(ChunkingSelection::new(strategy)), "m", 3, true)
                    .is_ok(),
                "{strategy}"
            );
        }
    }
}
