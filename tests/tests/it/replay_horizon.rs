//! The trace-replay engine (`kairos_server::pool::replay`) against the simulator's replayed
//! horizon (`kairos_bench::sim::horizon`): a chunk replayed live gets, from the real horizon
//! policy, the horizon the simulator assumes for the same recorded round.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use kairos_bench::sim::horizon::{ReplayHorizon, confidence_for_target};
use kairos_core::action::{ActionManager, RoundContext};
use kairos_core::horizon::PolicyParams;
use kairos_core::registry::{HorizonRegistry, native_horizon_policies};
use kairos_engine::{ActionModel, ActionRequest, EngineProfile, ProfilePoint};
use kairos_sdk::trace::{HorizonSetting, RoundTrace};
use kairos_server::pool::replay::{TraceReplayModel, replay_state};

fn profile() -> EngineProfile {
    EngineProfile {
        model: "modelled".into(),
        device: "test".into(),
        points: vec![
            ProfilePoint {
                batch: 1,
                latency_ms: 20.0,
            },
            ProfilePoint {
                batch: 4,
                latency_ms: 50.0,
            },
        ],
        max_batch: 4,
    }
}

fn request(state: Vec<f32>) -> ActionRequest {
    ActionRequest {
        cameras: Vec::new(),
        state,
        images: Vec::new(),
        instruction: String::new(),
        samples: 1,
        seed: 0,
        guidance: None,
    }
}

fn round(confidence: Option<Vec<f32>>, horizon: u32) -> RoundTrace {
    RoundTrace {
        issued_at_action: 0,
        aligned_at_action: None,
        horizon,
        executed: horizon,
        gen_latency_us: 0,
        round_trip_us: None,
        obs_bytes: 100,
        confidence,
    }
}

#[test]
fn the_live_horizon_from_a_replayed_chunk_is_the_simulators() {
    let n = 50;
    let model = TraceReplayModel::new(n, profile()).unwrap();
    let params = PolicyParams::from([("t".to_string(), 0.4), ("h_min".to_string(), 5.0)]);
    let manager = ActionManager::new(
        HorizonRegistry::new(),
        &native_horizon_policies(),
        "threshold",
        params.clone(),
    )
    .unwrap();
    let setting = HorizonSetting {
        policy: "threshold".into(),
        params: params.clone(),
    };
    let mut sim = ReplayHorizon::new(&setting).unwrap();
    for target in [1, 5, 9, 17, 33, 50] {
        let recorded = round(Some(confidence_for_target(target, 0.4, n as u32)), target);
        let chunk = &model
            .generate(&[request(replay_state(&recorded, n))])
            .unwrap()[0];
        let mut policy = manager.build(Some("threshold"), Some(&params)).unwrap();
        let live = manager
            .choose(
                &mut policy,
                chunk,
                RoundContext {
                    control_hz: 20.0,
                    round_index: 0,
                    recent_horizons: &[],
                    load: None,
                },
            )
            .unwrap();
        let simulated = sim.choose(&recorded, 0, n as u32, 20.0).unwrap();
        assert_eq!(live.horizon as u32, simulated, "target {target}");
        assert_eq!(live.horizon, (target as usize).max(5));
    }
}
