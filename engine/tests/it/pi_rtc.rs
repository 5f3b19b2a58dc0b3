//! Real-time chunking and inpainting for π0 and π0.5 through the shared sampler, served
//! through `ActionModel` on both paths (fast kernels, Candle) from the `pi0_tiny` and
//! `pi05_tiny` fixtures.
//!
//! LeRobot 0.6.1 records no RTC goldens for π (its RTC processor is the same code for every
//! flow policy, and the sampler's guidance is checked against LeRobot's goldens on SmolVLA in
//! `smolvla_rtc.rs`); here the checks are what guidance must do whatever the network:
//! `inpaint` writes the committed actions exactly (through the normalisation and back), `rtc`
//! pulls the guided actions towards the committed ones, `rtc_vjp` is refused saying why, and a
//! guided request in a batch leaves the plain one beside it bit for bit as it is alone.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use kairos_engine::pi::PiPipeline;
use kairos_engine::{
    ActionChunk, ActionModel, ActionRequest, EngineOptions, Guidance, GuidanceMode, Kernels,
    PrefixSchedule,
};

use super::pi_parity::pi_fixture;

/// Committed actions the guidance names: the first rows of another seed's chunk.
const COMMITTED: usize = 6;
/// Of which the robot executes this many before the new chunk arrives.
const DELAY: usize = 2;

fn request(model: &PiPipeline, seed: u64, guidance: Option<Guidance>) -> ActionRequest {
    let obs = model.checkpoint().synthetic_observation();
    ActionRequest {
        cameras: obs.images.keys().cloned().collect(),
        images: obs.images.values().cloned().collect(),
        state: obs.state.clone(),
        instruction: obs.task.clone(),
        samples: 1,
        seed,
        guidance,
    }
}

fn guidance(mode: GuidanceMode, previous: &ActionChunk) -> Guidance {
    Guidance {
        mode,
        prefix: previous.actions[..COMMITTED * previous.action_dim].to_vec(),
        delay: DELAY,
        execution_horizon: COMMITTED,
        schedule: PrefixSchedule::Linear,
        max_guidance_weight: 10.0,
    }
}

/// `sum (a - b)^2` over the first `rows` actions.
fn distance(a: &ActionChunk, b: &[f32], rows: usize) -> f32 {
    let n = rows * a.action_dim;
    a.actions[..n]
        .iter()
        .zip(&b[..n])
        .map(|(x, y)| (x - y) * (x - y))
        .sum()
}

fn guided(fixture: &str, kernels: Kernels) {
    let options = EngineOptions {
        kernels,
        threads: 2,
        ..Default::default()
    };
    let model = PiPipeline::load(&pi_fixture(fixture), None, &options).unwrap();
    let support = model.chunking().guidance;
    assert!(support.supports(GuidanceMode::Rtc) && support.supports(GuidanceMode::Inpaint));
    assert!(!support.supports(GuidanceMode::RtcVjp));
    let generate = |requests: Vec<ActionRequest>| model.generate(&requests).unwrap();
    let previous = generate(vec![request(&model, 9, None)]).remove(0);
    let plain = generate(vec![request(&model, 5, None)]).remove(0);
    let committed = &previous.actions[..COMMITTED * previous.action_dim];
    let label = format!("{fixture} {kernels:?}");

    let rtc = guidance(GuidanceMode::Rtc, &previous);
    let pulled = generate(vec![request(&model, 5, Some(rtc.clone()))]).remove(0);
    let (before, after) = (
        distance(&plain, committed, COMMITTED),
        distance(&pulled, committed, COMMITTED),
    );
    eprintln!("{label}: rtc moves the guided actions from {before:.3e} to {after:.3e}");
    assert!(after < before, "{label}: rtc {after} >= plain {before}");

    let inpaint = guidance(GuidanceMode::Inpaint, &previous);
    let written = generate(vec![request(&model, 5, Some(inpaint))]).remove(0);
    let n = DELAY * written.action_dim;
    let scale = committed[..n].iter().fold(1.0f32, |m, v| m.max(v.abs()));
    for (got, want) in written.actions[..n].iter().zip(&committed[..n]) {
        assert!(
            (got - want).abs() <= 1e-5 * scale,
            "{label}: inpaint wrote {got}, committed {want}"
        );
    }

    let refused = model
        .generate(&[request(
            &model,
            5,
            Some(guidance(GuidanceMode::RtcVjp, &previous)),
        )])
        .unwrap_err()
        .to_string();
    assert!(
        refused.contains("rtc_vjp") && refused.contains("backward"),
        "{label}: {refused}"
    );

    let mixed = generate(vec![
        request(&model, 5, Some(rtc)),
        request(&model, 5, None),
    ]);
    assert_eq!(mixed[0], pulled, "{label}: the guided request in a batch");
    assert_eq!(
        mixed[1], plain,
        "{label}: the plain request beside a guided one"
    );
}

#[test]
fn pi0_applies_rtc_and_inpaint_on_both_paths() {
    guided("pi0_tiny", Kernels::Auto);
    guided("pi0_tiny", Kernels::Candle);
}

#[test]
fn pi05_applies_rtc_and_inpaint_on_both_paths() {
    guided("pi05_tiny", Kernels::Auto);
    guided("pi05_tiny", Kernels::Candle);
}
