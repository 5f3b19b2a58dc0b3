//! Real-time chunking and inpainting for π0 and π0.5 through the shared sampler, served
//! through `ActionModel` on both paths (fast kernels, Candle) from the `pi0_tiny` and
//! `pi05_tiny` fixtures.
//!
//! LeRobot 0.6.1 records no RTC goldens for π (its RTC processor is the same code for every
//! flow policy, and the sampler's guidance is checked against LeRobot's goldens on SmolVLA in
//! `smolvla_rtc.rs`); here the checks are what guidance must do whatever the network:
//! `inpaint` writes the committed actions exactly (through the normalisation and back), `rtc`
//! pulls the guided actions towards the committed ones, `rtc_vjp` is served on the Candle path
//! (its pullback is the transposed Jacobian of the velocity, checked against a finite
//! difference; with every weight zero it is plain sampling) and refused on the fast kernels
//! naming the path that serves it, and a guided request in a batch leaves the plain one beside
//! it bit for bit as it is alone.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use crate::vjp_check;
use kairos_engine::guidance::RowGuide;
use kairos_engine::pi::{FastSampleInput, PiObservation, PiPipeline, SampleInput};
use kairos_engine::{
    ActionChunk, ActionModel, ActionRequest, DeviceKind, EngineOptions, Guidance, GuidanceMode,
    Kernels, Precision, PrefixSchedule,
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
    guided_on(fixture, DeviceKind::Cpu, kernels);
}

fn guided_on(fixture: &str, device: DeviceKind, kernels: Kernels) {
    let options = EngineOptions {
        device,
        kernels,
        threads: 2,
        ..Default::default()
    };
    let model = PiPipeline::load(&pi_fixture(fixture), None, &options).unwrap();
    let support = model.chunking().guidance;
    assert!(support.supports(GuidanceMode::Rtc) && support.supports(GuidanceMode::Inpaint));
    assert_eq!(
        support.supports(GuidanceMode::RtcVjp),
        kernels == Kernels::Candle
    );
    let generate = |requests: Vec<ActionRequest>| model.generate(&requests).unwrap();
    let previous = generate(vec![request(&model, 9, None)]).remove(0);
    let plain = generate(vec![request(&model, 5, None)]).remove(0);
    let committed = &previous.actions[..COMMITTED * previous.action_dim];
    let label = format!("{fixture} {device:?}/{kernels:?}");

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

    let vjp = guidance(GuidanceMode::RtcVjp, &previous);
    if kernels == Kernels::Candle {
        let pulled_vjp = generate(vec![request(&model, 5, Some(vjp.clone()))]).remove(0);
        assert_ne!(pulled_vjp.actions, plain.actions, "{label}: rtc_vjp");
        assert_ne!(
            pulled_vjp.actions, pulled.actions,
            "{label}: rtc_vjp vs rtc"
        );
        // `zeros` with no delay weighs every action 0: the error, its pullback and so the
        // correction are zero, and the chunk is plain sampling's, bit for bit.
        let unweighted = Guidance {
            schedule: PrefixSchedule::Zeros,
            delay: 0,
            ..vjp.clone()
        };
        let chunk = generate(vec![request(&model, 5, Some(unweighted))]).remove(0);
        assert_eq!(chunk, plain, "{label}: rtc_vjp with zero weights");
        // The rows that need the backward pass run apart from the others: each row of a
        // mixed batch is what it is alone.
        let mixed = generate(vec![
            request(&model, 5, None),
            request(&model, 5, Some(vjp.clone())),
        ]);
        assert_eq!(mixed[0], plain, "{label}: the plain request beside rtc_vjp");
        assert_eq!(
            mixed[1], pulled_vjp,
            "{label}: rtc_vjp beside a plain request"
        );
    } else {
        let refused = model
            .generate(&[request(&model, 5, Some(vjp))])
            .unwrap_err()
            .to_string();
        assert!(
            refused.contains("rtc_vjp")
                && refused.contains("backward")
                && refused.contains("--kernels candle"),
            "{label}: {refused}"
        );
    }

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
fn pi0_applies_every_guidance_its_path_has() {
    guided("pi0_tiny", Kernels::Auto);
    guided("pi0_tiny", Kernels::Candle);
}

#[test]
fn pi05_applies_every_guidance_its_path_has() {
    guided("pi05_tiny", Kernels::Auto);
    guided("pi05_tiny", Kernels::Candle);
}

/// The same on CUDA, where only the Candle path runs.
#[cfg(feature = "cuda")]
#[test]
fn pi_guidance_on_cuda() {
    guided_on("pi0_tiny", DeviceKind::Cuda(0), Kernels::Candle);
    guided_on("pi05_tiny", DeviceKind::Cuda(0), Kernels::Candle);
}

fn model_options(kernels: Kernels) -> EngineOptions {
    EngineOptions {
        kernels,
        threads: 2,
        precision: Precision::F32,
        ..Default::default()
    }
}

/// The pullback `rtc_vjp` takes from Candle's autograd through π's velocity network (π0: with
/// the state token and the action-time MLP; π0.5: with the adaRMS condition, a constant of `t`)
/// is the transposed Jacobian of the velocity applied to the guidance error: its inner product
/// with a direction `e` agrees with a central difference of `<v(x), c>` along `e`. The fast
/// kernels refuse the same row, naming the path that serves it.
///
/// The check and its bound: [`vjp_check`].
fn vjp_matches_a_finite_difference(fixture: &str) {
    let candle =
        PiPipeline::load(&pi_fixture(fixture), None, &model_options(Kernels::Candle)).unwrap();
    let fast = PiPipeline::load(&pi_fixture(fixture), None, &model_options(Kernels::Auto)).unwrap();
    let (model, fast_model) = (candle.candle_model().unwrap(), fast.fast_model().unwrap());
    let d = model.dims().clone();
    let len = d.chunk * d.action_pad;
    let prepared = candle
        .checkpoint()
        .prepare(&candle.checkpoint().synthetic_observation())
        .unwrap();
    let observation = PiObservation {
        images: prepared
            .images
            .iter()
            .map(|img| img.present.then_some(img.pixels.as_slice()))
            .collect(),
        tokens: &prepared.tokens.ids,
        token_mask: &prepared.tokens.mask,
    };
    let prefix = model
        .prefix(std::slice::from_ref(&observation))
        .unwrap()
        .remove(0);
    let fast_prefix = fast_model.prefix(&[observation]).unwrap().remove(0);
    let noise = kairos_engine::sampler::gaussian_noise(5, 0, len);
    // Committed actions in the model's space (the check needs a target, not a robot's one).
    let action_dim = candle.action_dim();
    let committed = kairos_engine::sampler::gaussian_noise(9, 0, COMMITTED * action_dim);
    let guide = |mode| {
        let g = Guidance {
            mode,
            prefix: committed.clone(),
            delay: DELAY,
            execution_horizon: COMMITTED,
            schedule: PrefixSchedule::Linear,
            max_guidance_weight: 10.0,
        };
        RowGuide::prepare(&g, d.chunk, action_dim, d.action_pad, &noise, &|_| {}).unwrap()
    };
    let state = Some(prepared.state.as_slice());
    let first_velocity = |x: &[f32], guide: Option<RowGuide>| {
        let noise = [x.to_vec()];
        let input = SampleInput {
            prefix: &prefix,
            state,
            noise: &noise,
        };
        let guides: Vec<Option<RowGuide>> = guide.into_iter().map(Some).collect();
        model.sample_guided(&[input], &guides).unwrap()[0].velocities[..len].to_vec()
    };
    let noises = [noise.clone()];
    let fast_input = FastSampleInput {
        prefix: &fast_prefix,
        state,
        noise: &noises,
    };
    let refused = fast_model
        .sample_guided(&[fast_input], &[Some(guide(GuidanceMode::RtcVjp))])
        .unwrap_err()
        .to_string();
    assert!(
        refused.contains("rtc_vjp")
            && refused.contains("backward")
            && refused.contains("--kernels candle"),
        "{fixture}: {refused}"
    );

    let v_fast = fast_model
        .sample(&[fast_input])
        .unwrap()
        .remove(0)
        .velocities[..len]
        .to_vec();
    // Smaller than SmolVLA's 1e-2: the tiny π0's velocity bends enough that at 1e-2 the
    // truncation term alone is a quarter of the product; at 3e-3 truncation and rounding are
    // of one size.
    vjp_check::vjp_matches_a_finite_difference(
        fixture,
        &noise,
        first_velocity,
        guide,
        &v_fast,
        3e-3,
    );
}

#[test]
fn pi0_candle_vjp_matches_a_finite_difference_of_the_velocity() {
    vjp_matches_a_finite_difference("pi0_tiny");
}

#[test]
fn pi05_candle_vjp_matches_a_finite_difference_of_the_velocity() {
    vjp_matches_a_finite_difference("pi05_tiny");
}
