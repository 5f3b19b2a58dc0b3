//! Tests of the native horizon policies: hand-made `U` and property tests.

use proptest::prelude::*;

use super::*;

/// An owned chunk to build [`ChunkView`]s from.
#[derive(Clone, Debug)]
struct Chunk {
    samples: usize,
    steps: usize,
    chunk_len: usize,
    action_dim: usize,
    updates: Vec<f32>,
    actions: Vec<f32>,
}

impl Chunk {
    fn zeros(samples: usize, steps: usize, chunk_len: usize, action_dim: usize) -> Self {
        Chunk {
            samples,
            steps,
            chunk_len,
            action_dim,
            updates: vec![0.0; samples * steps * chunk_len * action_dim],
            actions: vec![0.0; samples * chunk_len * action_dim],
        }
    }

    /// Sets sample 0's update of action `n` at every step to the given vectors.
    fn set_updates(&mut self, n: usize, per_step: &[&[f32]]) {
        assert_eq!(per_step.len(), self.steps);
        for (k, v) in per_step.iter().enumerate() {
            let start = (k * self.chunk_len + n) * self.action_dim;
            self.updates[start..start + self.action_dim].copy_from_slice(v);
        }
    }

    fn set_action(&mut self, s: usize, n: usize, v: &[f32]) {
        let start = (s * self.chunk_len + n) * self.action_dim;
        self.actions[start..start + self.action_dim].copy_from_slice(v);
    }

    fn view(&self) -> ChunkView<'_> {
        ChunkView {
            samples: self.samples,
            steps: self.steps,
            chunk_len: self.chunk_len,
            action_dim: self.action_dim,
            updates: &self.updates,
            actions: &self.actions,
        }
    }
}

fn input<'a>(
    chunk: &'a Chunk,
    h_min: usize,
    h_max: usize,
    params: &'a PolicyParams,
) -> HorizonInput<'a> {
    HorizonInput {
        chunk: chunk.view(),
        h_min,
        h_max,
        control_hz: 30.0,
        round_index: 3,
        recent_horizons: &[],
        params,
        load: None,
    }
}

fn params(pairs: &[(&str, f64)]) -> PolicyParams {
    pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect()
}

fn choose(
    name: &str,
    build: &[(&str, f64)],
    chunk: &Chunk,
    h_min: usize,
    h_max: usize,
) -> Result<usize, HorizonError> {
    let mut policy = builtin(name, &params(build))?;
    let none = PolicyParams::new();
    let input = input(chunk, h_min, h_max, &none);
    let h = policy.choose(&input)?;
    validate_horizon(h, &input)
}

/// The paper's Fig. "confidence": six actions, K = 4 steps, D = 2. A1–A4 and A6 shrink
/// (norms 5, 2.5, 1.25, then 0.5 against an earlier mean of 2.9167); A5's earlier updates have
/// norm 2 and its final one norm 3: 50% above its mean, over the t = 0.4 threshold. H = 4.
fn confidence_figure() -> Chunk {
    let mut c = Chunk::zeros(1, 4, 6, 2);
    let converged: [&[f32]; 4] = [&[3.0, 4.0], &[1.5, 2.0], &[0.75, 1.0], &[0.3, 0.4]];
    for n in [0, 1, 2, 3, 5] {
        c.set_updates(n, &converged);
    }
    c.set_updates(4, &[&[0.0, 2.0], &[2.0, 0.0], &[0.0, -2.0], &[0.0, 3.0]]);
    c
}

#[test]
fn threshold_reproduces_the_papers_confidence_figure() {
    let c = confidence_figure();
    assert_eq!(threshold::threshold_prefix(&c.view(), 0.4), 4);
    assert_eq!(choose("threshold", &[("t", 0.4)], &c, 1, 6), Ok(4));
    assert_eq!(
        choose("threshold", &[], &c, 1, 6),
        Ok(4),
        "t defaults to 0.4"
    );
    // At t = 0.5 the final update is exactly (1+t) x the mean: not exceeding, all six converge.
    assert_eq!(choose("threshold", &[("t", 0.5)], &c, 1, 6), Ok(6));
    // H = max(H_thresh, H_min), capped at h_max.
    assert_eq!(choose("threshold", &[("h_min", 5.0)], &c, 1, 6), Ok(5));
    assert_eq!(
        choose("threshold", &[], &c, 5, 6),
        Ok(5),
        "the robot's h_min applies too"
    );
    assert_eq!(choose("threshold", &[("t", 0.5)], &c, 1, 3), Ok(3));
}

#[test]
fn threshold_edge_cases() {
    // N = 1, converged.
    let mut one = Chunk::zeros(1, 3, 1, 1);
    one.set_updates(0, &[&[2.0], &[1.0], &[0.5]]);
    assert_eq!(choose("threshold", &[], &one, 1, 1), Ok(1));
    // K = 1: no earlier steps, nothing exceeds, H = min(N, h_max).
    let mut k1 = Chunk::zeros(1, 1, 5, 1);
    for n in 0..5 {
        k1.set_updates(n, &[&[100.0]]);
    }
    assert_eq!(threshold::threshold_prefix(&k1.view(), 0.0), 5);
    assert_eq!(choose("threshold", &[], &k1, 1, 4), Ok(4));
    // All unconverged (growing updates): H_thresh = 0, so H = H_min.
    let mut grow = Chunk::zeros(1, 3, 4, 1);
    for n in 0..4 {
        grow.set_updates(n, &[&[1.0], &[1.0], &[5.0]]);
    }
    assert_eq!(threshold::threshold_prefix(&grow.view(), 0.4), 0);
    assert_eq!(choose("threshold", &[], &grow, 2, 4), Ok(2));
    assert_eq!(choose("threshold", &[("h_min", 3.0)], &grow, 1, 4), Ok(3));
    // All-zero updates: 0 <= (1+t)*0, converged.
    let zeros = Chunk::zeros(1, 3, 4, 2);
    assert_eq!(threshold::threshold_prefix(&zeros.view(), 0.4), 4);
    // A NaN counts as unconverged.
    let mut nan = confidence_figure();
    nan.set_updates(
        1,
        &[&[1.0, 0.0], &[1.0, 0.0], &[1.0, 0.0], &[f32::NAN, 0.0]],
    );
    assert_eq!(threshold::threshold_prefix(&nan.view(), 0.4), 1);
    // Samples beyond the first are ignored.
    let mut two = Chunk::zeros(2, 3, 2, 1);
    two.set_updates(0, &[&[1.0], &[1.0], &[0.5]]);
    two.set_updates(1, &[&[1.0], &[1.0], &[0.5]]);
    let sample1_start = 3 * 2;
    two.updates[sample1_start..].fill(f32::NAN);
    assert_eq!(threshold::threshold_prefix(&two.view(), 0.0), 2);
}

#[test]
fn parameters_are_validated() {
    let bad = |name: &str, p: &[(&str, f64)]| builtin(name, &params(p)).is_err();
    assert!(bad("threshold", &[("t", -0.1)]));
    assert!(bad("threshold", &[("t", f64::NAN)]));
    assert!(bad("threshold", &[("h_min", 0.0)]));
    assert!(bad("threshold", &[("h_min", 2.5)]));
    assert!(
        bad("threshold", &[("tt", 0.4)]),
        "unknown names are refused"
    );
    assert!(bad("static", &[]), "static needs h");
    assert!(bad("static", &[("h", 0.0)]));
    assert!(bad("spread", &[("threshold", -1.0)]));
    assert!(bad("nonsense", &[]));
    assert!(!bad("threshold", &[("t", 0.0), ("h_min", 4.0)]));
    assert!(!bad("spread", &[("threshold", 0.2), ("h_min", 1.0)]));
    // Per-call parameters override the built ones and are validated the same way.
    let c = confidence_figure();
    let mut policy = builtin("threshold", &PolicyParams::new()).unwrap();
    let per_call = params(&[("t", 0.5)]);
    assert_eq!(policy.choose(&input(&c, 1, 6, &per_call)), Ok(6));
    let wrong = params(&[("t", -3.0)]);
    assert!(policy.choose(&input(&c, 1, 6, &wrong)).is_err());
}

#[test]
fn inconsistent_inputs_are_unsupported() {
    let mut c = confidence_figure();
    c.updates.pop();
    assert!(matches!(
        choose("threshold", &[], &c, 1, 6),
        Err(HorizonError::Unsupported(_))
    ));
    let ok = confidence_figure();
    assert!(matches!(
        choose("threshold", &[], &ok, 5, 4),
        Err(HorizonError::Unsupported(_))
    ));
}

#[test]
fn static_clamps_h_to_the_robots_bounds() {
    let c = confidence_figure();
    assert_eq!(choose("static", &[("h", 3.0)], &c, 1, 6), Ok(3));
    assert_eq!(choose("static", &[("h", 50.0)], &c, 1, 5), Ok(5));
    assert_eq!(choose("static", &[("h", 1.0)], &c, 2, 6), Ok(2));
}

#[test]
fn spread_cuts_where_samples_disagree() {
    // Two samples, D = 1. Spreads: n0 = 0.05, n1 = 0.15, n2 = 0.
    let mut c = Chunk::zeros(2, 1, 3, 1);
    c.set_action(1, 0, &[0.1]);
    c.set_action(1, 1, &[0.3]);
    let v = c.view();
    assert!((spread::action_spread(&v, 0) - 0.05).abs() < 1e-8);
    assert!((spread::action_spread(&v, 1) - 0.15).abs() < 1e-8);
    assert_eq!(spread::action_spread(&v, 2), 0.0);
    assert_eq!(
        choose("spread", &[], &c, 1, 3),
        Ok(1),
        "n1 exceeds the default 0.1"
    );
    assert_eq!(choose("spread", &[("threshold", 0.2)], &c, 1, 3), Ok(3));
    assert_eq!(choose("spread", &[("h_min", 2.0)], &c, 1, 3), Ok(2));
    // RMS over dimensions: D = 2 with stds 0.3 and 0.4 -> sqrt((0.09 + 0.16) / 2).
    let mut d2 = Chunk::zeros(2, 1, 1, 2);
    d2.set_action(0, 0, &[-0.3, 0.4]);
    d2.set_action(1, 0, &[0.3, -0.4]);
    let expected = ((0.09f64 + 0.16) / 2.0).sqrt();
    assert!((spread::action_spread(&d2.view(), 0) - expected).abs() < 1e-7);
    // One sample cannot show a spread.
    let single = Chunk::zeros(1, 1, 3, 1);
    assert!(matches!(
        choose("spread", &[], &single, 1, 3),
        Err(HorizonError::Unsupported(_))
    ));
}

#[test]
fn threshold_reads_the_chosen_denoising_step() {
    // K = 4, one action: updates of norm 1, 1, 5, 1. Reading the final step (mean of the three
    // before = 7/3, final 1) converges; reading step 2 (mean 1, update 5) does not; step 1
    // (mean 1, update 1) converges; a step past the last reads the last.
    let mut c = Chunk::zeros(1, 4, 1, 1);
    c.set_updates(0, &[&[1.0], &[1.0], &[5.0], &[1.0]]);
    let v = c.view();
    assert_eq!(threshold::threshold_prefix(&v, 0.4), 1);
    assert_eq!(threshold::threshold_prefix_at(&v, 0.4, Some(2)), 0);
    assert_eq!(threshold::threshold_prefix_at(&v, 0.4, Some(1)), 1);
    assert_eq!(threshold::threshold_prefix_at(&v, 0.4, Some(99)), 1);
    assert_eq!(threshold::threshold_prefix_at(&v, 0.4, Some(3)), 1);
    let mut two = Chunk::zeros(1, 4, 2, 1);
    two.set_updates(0, &[&[1.0], &[1.0], &[1.0], &[1.0]]);
    two.set_updates(1, &[&[1.0], &[1.0], &[5.0], &[1.0]]);
    assert_eq!(choose("threshold", &[("step", 2.0)], &two, 1, 2), Ok(1));
    assert_eq!(choose("threshold", &[], &two, 1, 2), Ok(2));
    let bad = |p: &[(&str, f64)]| builtin("threshold", &params(p)).is_err();
    assert!(
        bad(&[("step", 0.0)]),
        "step 0 has no earlier steps to compare with"
    );
    assert!(bad(&[("step", 1.5)]));
}

/// One sample, D = 2: actions `[1, 0]` repeated, then a change at action `at` to `[0, 1]`.
fn turning_chunk(n: usize, at: usize) -> Chunk {
    let mut c = Chunk::zeros(1, 1, n, 2);
    for i in 0..n {
        c.set_action(0, i, if i < at { &[1.0, 0.0] } else { &[0.0, 1.0] });
    }
    c
}

#[test]
fn steady_cuts_margin_actions_before_the_chunk_changes_course() {
    let c = turning_chunk(8, 5); // jump_5 = sqrt(2)
    let v = c.view();
    assert_eq!(steady::first_change(&v, 0.25), 5);
    assert!((steady::action_jump(&v, 5) - 2f64.sqrt()).abs() < 1e-12);
    assert_eq!(steady::action_jump(&v, 3), 0.0);
    assert_eq!(
        choose("steady", &[], &c, 1, 8),
        Ok(4),
        "margin defaults to 1"
    );
    assert_eq!(choose("steady", &[("margin", 0.0)], &c, 1, 8), Ok(5));
    assert_eq!(choose("steady", &[("margin", 3.0)], &c, 1, 8), Ok(2));
    assert_eq!(
        choose("steady", &[("margin", 9.0)], &c, 1, 8),
        Ok(1),
        "never below h_min"
    );
    assert_eq!(
        choose("steady", &[("margin", 9.0), ("h_min", 3.0)], &c, 1, 8),
        Ok(3)
    );
    // A delta above the jump sees no change: the whole chunk, up to the caps.
    assert_eq!(choose("steady", &[("delta", 1.5)], &c, 1, 8), Ok(7));
    assert_eq!(
        choose("steady", &[("delta", 1.5), ("margin", 0.0)], &c, 1, 8),
        Ok(8)
    );
    assert_eq!(
        choose("steady", &[("delta", 1.5), ("h_max", 3.0)], &c, 1, 8),
        Ok(3)
    );
    assert_eq!(choose("steady", &[("delta", 1.5)], &c, 1, 6), Ok(6));
    // An h_max below h_min is raised to it.
    assert_eq!(
        choose("steady", &[("h_max", 1.0), ("h_min", 2.0)], &c, 1, 8),
        Ok(2)
    );
    // Exactly delta is still steady; a NaN is a change.
    let mut edge = Chunk::zeros(1, 1, 4, 1);
    for (i, x) in [0.0f32, 0.5, 1.0, 1.5].iter().enumerate() {
        edge.set_action(0, i, &[*x]);
    }
    assert_eq!(steady::first_change(&edge.view(), 0.5), 4);
    edge.set_action(0, 2, &[f32::NAN]);
    assert_eq!(steady::first_change(&edge.view(), 0.5), 2);
    // Only sample 0 is read.
    let mut two = Chunk::zeros(2, 1, 4, 1);
    two.set_action(1, 2, &[9.0]);
    assert_eq!(steady::first_change(&two.view(), 0.1), 4);
    let bad = |p: &[(&str, f64)]| builtin("steady", &params(p)).is_err();
    assert!(bad(&[("delta", -0.1)]));
    assert!(bad(&[("margin", 0.5)]));
    assert!(bad(&[("margin", -1.0)]));
    assert!(bad(&[("h_max", 0.0)]));
    assert!(bad(&[("jump", 0.3)]));
    assert!(!bad(&[
        ("delta", 0.0),
        ("margin", 0.0),
        ("h_min", 1.0),
        ("h_max", 4.0)
    ]));
}

fn arb_chunk() -> impl Strategy<Value = Chunk> {
    (1usize..4, 1usize..6, 1usize..12, 1usize..5).prop_flat_map(|(s, k, n, d)| {
        (
            proptest::collection::vec(-4.0f32..4.0, s * k * n * d),
            proptest::collection::vec(-1.0f32..1.0, s * n * d),
        )
            .prop_map(move |(updates, actions)| Chunk {
                samples: s,
                steps: k,
                chunk_len: n,
                action_dim: d,
                updates,
                actions,
            })
    })
}

proptest! {
    #[test]
    fn every_policy_answers_within_the_robots_bounds(
        c in arb_chunk(),
        t in 0.0f64..2.0,
        h in 1usize..60,
        lo in 1usize..12,
        span in 0usize..12,
    ) {
        let h_max = (lo + span).min(c.chunk_len);
        prop_assume!(lo <= h_max);
        for (name, p) in [
            ("threshold", params(&[("t", t)])),
            ("static", params(&[("h", h as f64)])),
            ("spread", params(&[("threshold", t)])),
            ("steady", params(&[("delta", t), ("margin", (h % 4) as f64)])),
            ("contact", params(&[("slow", t), ("margin", (h % 4) as f64)])),
            ("threshold", params(&[("t", t), ("step", (h % 5 + 1) as f64)])),
        ] {
            let mut policy = builtin(name, &p).unwrap();
            let none = PolicyParams::new();
            let inp = input(&c, lo, h_max, &none);
            match policy.choose(&inp) {
                Ok(answer) => prop_assert_eq!(validate_horizon(answer, &inp), Ok(answer)),
                Err(HorizonError::Unsupported(_)) => prop_assert!(name == "spread" && c.samples < 2),
                Err(e) => prop_assert!(false, "{name}: {e}"),
            }
        }
    }

    #[test]
    fn a_larger_threshold_never_shortens_the_prefix(c in arb_chunk(), t in 0.0f64..1.0, dt in 0.0f64..1.0) {
        let v = c.view();
        prop_assert!(threshold::threshold_prefix(&v, t) <= threshold::threshold_prefix(&v, t + dt));
        prop_assert!(spread::spread_prefix(&v, t) <= spread::spread_prefix(&v, t + dt));
        prop_assert!(steady::first_change(&v, t) <= steady::first_change(&v, t + dt));
        // A larger `slow` counts more actions as slow: the contact comes no later.
        prop_assert!(contact::first_contact(&v, t + dt) <= contact::first_contact(&v, t));
    }

    #[test]
    fn scaling_all_updates_by_a_power_of_two_keeps_the_threshold_prefix(c in arb_chunk(), t in 0.0f64..1.0, e in -8i32..8) {
        let mut scaled = c.clone();
        let f = 2f32.powi(e);
        scaled.updates.iter_mut().for_each(|x| *x *= f);
        prop_assert_eq!(
            threshold::threshold_prefix(&c.view(), t),
            threshold::threshold_prefix(&scaled.view(), t)
        );
    }

    #[test]
    fn identical_samples_have_no_spread(c in arb_chunk()) {
        let mut same = c.clone();
        let per_sample = c.chunk_len * c.action_dim;
        let first: Vec<f32> = c.actions[..per_sample].to_vec();
        for s in 0..c.samples {
            same.actions[s * per_sample..(s + 1) * per_sample].copy_from_slice(&first);
        }
        prop_assert_eq!(spread::spread_prefix(&same.view(), 0.0), c.chunk_len);
    }
}

/// One sample, D = 3 (velocity x, y, gripper): full speed with the gripper open, slowing to
/// `slow_speed` from action `slows`, the gripper closing at action `closes`.
fn approach_chunk(n: usize, slows: usize, closes: usize, slow_speed: f32) -> Chunk {
    let mut c = Chunk::zeros(1, 1, n, 3);
    for i in 0..n {
        let speed = if i < slows { 1.0 } else { slow_speed };
        let gripper = if i < closes { -1.0 } else { 1.0 };
        // A 3-4-5 direction, so the speed is exact.
        c.set_action(0, i, &[0.6 * speed, -0.8 * speed, gripper]);
    }
    c
}

#[test]
fn contact_cuts_margin_actions_before_the_plan_slows_or_switches_the_gripper() {
    // Slows at 6, closes at 9: the event is 6.
    let c = approach_chunk(12, 6, 9, 0.3);
    let v = c.view();
    assert!((contact::planned_speed(&v, 0) - 1.0).abs() < 1e-6);
    assert!((contact::planned_speed(&v, 7) - 0.3).abs() < 1e-6);
    assert!(!contact::gripper_switches(&v, 8) && contact::gripper_switches(&v, 9));
    assert_eq!(contact::first_contact(&v, 0.5), 6);
    assert_eq!(choose("contact", &[], &c, 1, 12), Ok(5), "margin 1");
    assert_eq!(choose("contact", &[("margin", 0.0)], &c, 1, 12), Ok(6));
    // A slow threshold below the slow speed: only the gripper's switch is an event.
    assert_eq!(contact::first_contact(&v, 0.2), 9);
    assert_eq!(
        choose("contact", &[("slow", 0.2), ("margin", 2.0)], &c, 1, 12),
        Ok(7)
    );
    // Already slow at action 0 (inside the contact phase): h_min.
    let inside = approach_chunk(12, 0, 12, 0.3);
    assert_eq!(contact::first_contact(&inside.view(), 0.5), 0);
    assert_eq!(choose("contact", &[], &inside, 1, 12), Ok(1));
    assert_eq!(choose("contact", &[("h_min", 2.0)], &inside, 1, 12), Ok(2));
    // No event: the whole chunk, up to the caps.
    let transit = approach_chunk(12, 12, 12, 0.3);
    assert_eq!(contact::first_contact(&transit.view(), 0.5), 12);
    assert_eq!(choose("contact", &[], &transit, 1, 12), Ok(11));
    assert_eq!(
        choose("contact", &[("margin", 0.0)], &transit, 1, 10),
        Ok(10)
    );
    assert_eq!(choose("contact", &[("h_max", 4.0)], &transit, 1, 12), Ok(4));
    // A gripper that was closed from the start (carrying) is not an event; opening it is.
    let mut carry = approach_chunk(12, 12, 0, 0.3);
    assert_eq!(contact::first_contact(&carry.view(), 0.5), 12);
    carry.set_action(0, 7, &[0.6, -0.8, -1.0]);
    assert_eq!(contact::first_contact(&carry.view(), 0.5), 7);
    // A NaN speed counts as slow.
    carry.set_action(0, 3, &[f32::NAN, 0.0, 1.0]);
    assert_eq!(contact::first_contact(&carry.view(), 0.5), 3);
    // Parameters are checked.
    let bad = |p: &[(&str, f64)]| builtin("contact", &params(p)).is_err();
    assert!(bad(&[("slow", -0.1)]));
    assert!(bad(&[("margin", 1.5)]));
    assert!(bad(&[("h_max", 0.0)]));
    assert!(bad(&[("delta", 0.3)]));
    assert!(!bad(&[
        ("slow", 0.0),
        ("margin", 0.0),
        ("h_min", 2.0),
        ("h_max", 8.0)
    ]));
}

/// `samples` samples of a placement: slow (0.3) and holding from action 0, and sample `s`
/// opening the gripper at `opens[s]` (`None`: it keeps holding).
fn placement_chunk(n: usize, opens: &[Option<usize>]) -> Chunk {
    let mut c = Chunk::zeros(opens.len(), 1, n, 3);
    for (s, open) in opens.iter().enumerate() {
        for i in 0..n {
            let gripper = if open.is_some_and(|o| i >= o) {
                -1.0
            } else {
                1.0
            };
            c.set_action(s, i, &[0.18, -0.24, gripper]);
        }
    }
    c
}

#[test]
fn contact_executes_through_a_release_the_samples_agree_on() {
    // Three of four samples release at action 3, one keeps holding.
    let mut c = placement_chunk(12, &[Some(3), Some(3), Some(3), None]);
    let v = c.view();
    assert_eq!(contact::first_contact(&v, 0.5), 0, "slow from action 0");
    assert_eq!(contact::planned_releases(&v, 4), 3);
    assert_eq!(
        contact::planned_releases(&v, 3),
        3,
        "the window includes action R"
    );
    assert_eq!(
        contact::planned_releases(&v, 2),
        0,
        "the release is outside the window"
    );
    assert_eq!(
        choose("contact", &[], &c, 1, 12),
        Ok(1),
        "release off: h_min"
    );
    let with = |release: f64, quorum: f64| {
        choose(
            "contact",
            &[("release", release), ("quorum", quorum)],
            &c,
            1,
            12,
        )
    };
    assert_eq!(with(4.0, 3.0), Ok(4), "through the release");
    assert_eq!(with(4.0, 4.0), Ok(1), "not enough samples agree");
    assert_eq!(with(2.0, 1.0), Ok(1), "no release within 2 actions");
    // The default quorum is one sample; the robot's and the param's caps still apply.
    assert_eq!(choose("contact", &[("release", 5.0)], &c, 1, 12), Ok(5));
    assert_eq!(choose("contact", &[("release", 5.0)], &c, 1, 3), Ok(3));
    assert_eq!(
        choose("contact", &[("release", 5.0), ("h_max", 2.0)], &c, 1, 12),
        Ok(2)
    );
    // A release never shortens what the cut rule already executes (a fast chunk: 11).
    let transit = approach_chunk(12, 12, 12, 0.3);
    assert_eq!(
        choose("contact", &[("release", 4.0)], &transit, 1, 12),
        Ok(11)
    );
    // A sample that is open at action 0 is not holding: it plans no release; a NaN gripper
    // command counts as open.
    c.set_action(0, 0, &[0.18, -0.24, -1.0]);
    assert_eq!(contact::planned_releases(&c.view(), 4), 2);
    c.set_action(3, 2, &[0.18, -0.24, f32::NAN]);
    assert_eq!(contact::planned_releases(&c.view(), 4), 3);
    // Parameters are checked.
    let bad = |p: &[(&str, f64)]| builtin("contact", &params(p)).is_err();
    assert!(bad(&[("release", 0.0)]));
    assert!(bad(&[("release", 2.5)]));
    assert!(bad(&[("release", 4.0), ("quorum", 0.0)]));
    assert!(!bad(&[("release", 4.0), ("quorum", 6.0)]));
}
