//! Every shipped plugin gives exactly the answer of its native twin, on the same randomized
//! inputs: `threshold`, `static`, `steady` and `contact` (C), `fifo`, `plas`, `kairos` and `srw` (C), and `kairos`
//! again in Python. `srw` learns from finished tasks, so both twins are told the same ones
//! between decisions and must keep agreeing as their Gittins indexes evolve. Run
//! `plugins/build.sh` first (CI does); a missing plugin fails the test.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::time::Duration;

use kairos_core::horizon::contact::ContactAware;
use kairos_core::horizon::fixed::StaticHorizon;
use kairos_core::horizon::steady::Steady;
use kairos_core::horizon::threshold::Threshold;
use kairos_core::horizon::{HorizonPolicy, PolicyParams};
use kairos_core::scheduler::{
    FinishedTask, PendingView, PolicySpec, PriorityPolicy, RemainingWork, RequestId, TaskId,
    build_policy,
};
use kairos_core::time::Timestamp;
use kairos_server::plugin::conformance::{HorizonCase, UpdateShape, horizon_case, horizon_cases};
use kairos_server::plugin::{FailureKind, PluginOptions, PluginSource, WasmPriorityPolicy};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::plugin_common::{Unreachable, horizon_plugin, options, same_answer, shipped_plugin};

/// Random chunks whose convergence varies along the chunk, so `H_thresh` lands anywhere.
fn threshold_inputs(seed: u64, count: usize) -> Vec<HorizonCase> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut cases = horizon_cases(seed, count);
    for i in 0..count {
        let dims = (
            1,
            rng.random_range(1..=12),
            rng.random_range(1..=60),
            rng.random_range(1..=10),
        );
        let shape = [
            UpdateShape::Realistic,
            UpdateShape::AllConverged,
            UpdateShape::AllUnconverged,
        ][i % 3];
        let mut case = horizon_case(&mut rng, format!("shaped #{i}"), "shaped", dims, shape);
        // Final-step ratios around 1+t from a random action on, so the cut lands inside.
        let (_, k, n, d) = case.dims;
        if k >= 2 {
            let norm = |v: &[f32]| v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
            let cut = rng.random_range(0..n);
            for action in cut..n {
                let at = |step: usize| (step * n + action) * d;
                let mean = (0..k - 1)
                    .map(|s| norm(&case.updates[at(s)..at(s) + d]))
                    .sum::<f64>()
                    / (k - 1) as f64;
                let last = norm(&case.updates[at(k - 1)..at(k - 1) + d]);
                if last > 0.0 {
                    let scale = (rng.random_range(0.6..2.0) * mean / last) as f32;
                    case.updates[at(k - 1)..at(k - 1) + d]
                        .iter_mut()
                        .for_each(|x| *x *= scale);
                }
            }
            case.bounds = (1, n);
        }
        cases.push(case);
    }
    cases
}

fn random_threshold_params(rng: &mut StdRng, n: usize) -> PolicyParams {
    let mut params = PolicyParams::new();
    match rng.random_range(0..10) {
        0 => {}
        1 => {
            params.insert("t".into(), -0.5);
        }
        2 => {
            params.insert("h_min".into(), 2.5);
        }
        3 => {
            params.insert("tau".into(), 0.4);
        }
        4 => {
            params.insert("t".into(), f64::NAN);
        }
        5 => {
            params.insert("step".into(), 0.0);
        }
        _ => {
            params.insert(
                "t".into(),
                [0.0, 0.1, 0.4, 1.0, rng.random_range(0.0..2.0)][rng.random_range(0..5)],
            );
            if rng.random_bool(0.5) {
                params.insert("h_min".into(), rng.random_range(1..=n + 3) as f64);
            }
            if rng.random_bool(0.4) {
                // Which denoising step is read; past the last one it reads the last.
                params.insert("step".into(), rng.random_range(1..=12) as f64);
            }
        }
    }
    params
}

/// Chunks whose final-step norms sit within a few ulps of `(1 + t) ×` their earlier mean: the
/// answer then depends on every rounding step, which is what "bit for bit" has to survive.
fn knife_edge_inputs(seed: u64, count: usize, t: f64) -> Vec<HorizonCase> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..count)
        .map(|i| {
            let dims = (
                1,
                rng.random_range(2..=12),
                rng.random_range(2..=50),
                rng.random_range(1..=8),
            );
            let mut case = horizon_case(
                &mut rng,
                format!("knife edge #{i}"),
                "edge",
                dims,
                UpdateShape::Realistic,
            );
            let (_, k, n, d) = case.dims;
            let norm = |v: &[f32]| v.iter().map(|x| f64::from(*x).powi(2)).sum::<f64>().sqrt();
            for action in 0..n {
                let at = |step: usize| (step * n + action) * d;
                let mean = (0..k - 1)
                    .map(|s| norm(&case.updates[at(s)..at(s) + d]))
                    .sum::<f64>()
                    / (k - 1) as f64;
                let last = norm(&case.updates[at(k - 1)..at(k - 1) + d]);
                if last > 0.0 {
                    let nudge =
                        1.0 + f64::from(rng.random_range(-7i32..=1)) * f64::from(f32::EPSILON);
                    let scale = ((1.0 + t) * mean / last * nudge) as f32;
                    case.updates[at(k - 1)..at(k - 1) + d]
                        .iter_mut()
                        .for_each(|x| *x *= scale);
                }
            }
            case.bounds = (1, n);
            case
        })
        .collect()
}

#[test]
fn threshold_plugin_matches_its_native_twin_on_knife_edges() {
    let mut plugin = horizon_plugin("threshold");
    let mut native = Threshold::default();
    let mut answers = std::collections::BTreeSet::new();
    for (t, params) in [
        (0.4, PolicyParams::new()),
        (0.1, [("t".to_string(), 0.1)].into()),
    ] {
        for case in knife_edge_inputs(17, 400, t) {
            let input = case.input(&params);
            let want = native.choose(&input);
            let (got, _) = plugin
                .call_plugin(&input)
                .unwrap_or_else(|f| panic!("{}: {f}", case.name));
            assert_eq!(want, got, "{}: t = {t}", case.name);
            answers.insert(want.unwrap());
        }
    }
    assert!(
        answers.len() > 10,
        "the cuts should land all over the chunk: {answers:?}"
    );
}

#[test]
fn threshold_plugin_matches_its_native_twin() {
    let mut plugin = horizon_plugin("threshold");
    let mut native = Threshold::default();
    let mut rng = StdRng::seed_from_u64(11);
    let mut decided = 0;
    let mut cut_inside = 0;
    for case in threshold_inputs(7, 400) {
        let params = random_threshold_params(&mut rng, case.dims.2);
        let input = case.input(&params);
        let want = native.choose(&input);
        let (got, _) = plugin
            .call_plugin(&input)
            .unwrap_or_else(|f| panic!("{}: {f}", case.name));
        assert!(
            same_answer(&want, &got),
            "{}: native {want:?}, plugin {got:?}, params {params:?}",
            case.name
        );
        decided += usize::from(want.is_ok());
        // Answers strictly inside the bounds come from the threshold itself, not a clamp.
        if let Ok(h) = want {
            cut_inside += usize::from(h > input.h_min.max(1) && h < input.h_max);
        }
    }
    assert!(
        decided > 400,
        "too few valid decisions to compare: {decided}"
    );
    assert!(
        cut_inside > 50,
        "too few threshold cuts inside the bounds: {cut_inside}"
    );
}

#[test]
fn static_plugin_matches_its_native_twin() {
    let mut plugin = horizon_plugin("static");
    let mut rng = StdRng::seed_from_u64(12);
    for case in horizon_cases(8, 300) {
        let n = case.dims.2;
        let mut params = PolicyParams::new();
        match rng.random_range(0..8) {
            0 => {}
            1 => {
                params.insert("h".into(), 0.0);
            }
            2 => {
                params.insert("x".into(), 3.0);
                params.insert("h".into(), 3.0);
            }
            _ => {
                params.insert("h".into(), rng.random_range(1..=n + 5) as f64);
            }
        }
        let input = case.input(&params);
        // The native policy reads `h` from the call's parameters, like the plugin.
        let want = match StaticHorizon::from_params(&params) {
            Ok(mut native) => native.choose(&input),
            Err(e) => Err(e),
        };
        let (got, _) = plugin
            .call_plugin(&input)
            .unwrap_or_else(|f| panic!("{}: {f}", case.name));
        assert!(
            same_answer(&want, &got),
            "{}: native {want:?}, plugin {got:?}, params {params:?}",
            case.name
        );
    }
}

/// Chunks whose sample-0 actions walk with steps around `delta`: some consecutive pairs a few
/// ulps either side of it, some far above (a turn), some NaN, so the cut lands anywhere.
fn steady_inputs(seed: u64, count: usize) -> Vec<(HorizonCase, PolicyParams)> {
    let mut rng = StdRng::seed_from_u64(seed);
    horizon_cases(seed, count)
        .into_iter()
        .map(|mut case| {
            let (_, _, n, d) = case.dims;
            let delta: f64 =
                [0.0, 0.1, 0.25, 0.5, rng.random_range(0.0..2.0)][rng.random_range(0..5)];
            for action in 1..n {
                let jump = match rng.random_range(0..10) {
                    0 => 4.0 * delta + 1.0,
                    1 => delta * (1.0 + f64::from(rng.random_range(-3i32..=3)) * f64::EPSILON),
                    _ => rng.random_range(0.0..=1.0) * delta,
                };
                // One dimension carries the whole jump, so its norm is |jump| up to rounding.
                let dim = rng.random_range(0..d);
                for i in 0..d {
                    let prev = case.actions[(action - 1) * d + i];
                    case.actions[action * d + i] = if i == dim { prev + jump as f32 } else { prev };
                }
            }
            if rng.random_bool(0.05) {
                let at = rng.random_range(0..n * d);
                case.actions[at] = f32::NAN;
            }
            let params = cut_rule_params(
                &mut rng,
                n,
                ("delta", delta),
                [
                    ("margin", 1.5),
                    ("delta", -0.1),
                    ("h_max", 0.0),
                    ("jump", 0.3),
                ],
            );
            if rng.random_bool(0.7) {
                case.bounds = (1, n);
            }
            (case, params)
        })
        .collect()
}

/// Parameters for a "cut before an event" rule (`steady`, `contact`) with chunks of `n` actions:
/// none (1 in 12), one of the four `invalid` settings alone (1 in 12 each: a fractional margin,
/// a negative real parameter, a zero count, an unknown name), or else the rule's `real`
/// parameter with a random margin and, sometimes, `h_min` and `h_max` (possibly beyond `n`).
fn cut_rule_params(
    rng: &mut StdRng,
    n: usize,
    real: (&str, f64),
    invalid: [(&str, f64); 4],
) -> PolicyParams {
    let mut params = PolicyParams::new();
    match rng.random_range(0..12) {
        0 => {}
        i @ 1..=4 => {
            let (name, value) = invalid[i - 1];
            params.insert(name.into(), value);
        }
        _ => {
            params.insert(real.0.into(), real.1);
            params.insert("margin".into(), rng.random_range(0..=3) as f64);
            if rng.random_bool(0.4) {
                params.insert("h_min".into(), rng.random_range(1..=n + 2) as f64);
            }
            if rng.random_bool(0.5) {
                params.insert("h_max".into(), rng.random_range(1..=n + 2) as f64);
            }
        }
    }
    params
}

/// Asserts that the shipped plugin `name` answers every input as `native` does, with enough
/// valid decisions and cuts strictly inside the bounds that the comparison means something.
fn assert_twins(
    name: &str,
    native: &mut dyn HorizonPolicy,
    inputs: Vec<(HorizonCase, PolicyParams)>,
) {
    let mut plugin = horizon_plugin(name);
    let (mut decided, mut cut_inside) = (0, 0);
    for (case, params) in inputs {
        let input = case.input(&params);
        let want = native.choose(&input);
        let (got, _) = plugin
            .call_plugin(&input)
            .unwrap_or_else(|f| panic!("{}: {f}", case.name));
        assert!(
            same_answer(&want, &got),
            "{}: native {want:?}, plugin {got:?}, params {params:?}",
            case.name
        );
        decided += usize::from(want.is_ok());
        if let Ok(h) = want {
            cut_inside += usize::from(h > input.h_min.max(1) && h < input.h_max.min(case.dims.2));
        }
    }
    assert!(decided > 300, "{name}: too few valid decisions: {decided}");
    assert!(
        cut_inside > 50,
        "{name}: too few cuts inside the bounds: {cut_inside}"
    );
}

#[test]
fn steady_plugin_matches_its_native_twin() {
    assert_twins("steady", &mut Steady::default(), steady_inputs(21, 600));
}

/// Chunks whose sample-0 actions have speeds (norm of all dimensions but the last) around
/// `slow` — some a few ulps either side of it, some far below — and a gripper (the last
/// dimension) that now and then switches sign or sits at exactly 0, some NaN, so the cut lands
/// anywhere.
fn contact_inputs(seed: u64, count: usize) -> Vec<(HorizonCase, PolicyParams)> {
    let mut rng = StdRng::seed_from_u64(seed);
    horizon_cases(seed, count)
        .into_iter()
        .map(|mut case| {
            let (_, _, n, d) = case.dims;
            let slow: f64 = [0.0, 0.25, 0.5, rng.random_range(0.0..1.5)][rng.random_range(0..4)];
            let mut gripper = if rng.random_bool(0.5) { 1.0f32 } else { -1.0 };
            for action in 0..n {
                let speed = match rng.random_range(0..12) {
                    0 => rng.random_range(0.0..=1.0) * slow,
                    1 => slow * (1.0 + f64::from(rng.random_range(-3i32..=3)) * f64::EPSILON),
                    _ => slow + rng.random_range(0.0..1.0),
                };
                let row = &mut case.actions[action * d..(action + 1) * d];
                // One velocity dimension carries the whole speed, so the norm is |speed| up to
                // the f32 rounding; the others are 0.
                let dim = rng.random_range(0..d.max(2) - 1);
                for (i, x) in row.iter_mut().enumerate() {
                    *x = if i + 1 == d {
                        0.0
                    } else if i == dim {
                        speed as f32 * if rng.random_bool(0.5) { 1.0 } else { -1.0 }
                    } else {
                        0.0
                    };
                }
                if rng.random_bool(0.08) {
                    gripper = -gripper;
                }
                row[d - 1] = if rng.random_bool(0.05) { 0.0 } else { gripper };
            }
            if rng.random_bool(0.05) {
                let at = rng.random_range(0..n * d);
                case.actions[at] = f32::NAN;
            }
            let params = cut_rule_params(
                &mut rng,
                n,
                ("slow", slow),
                [
                    ("margin", 0.5),
                    ("slow", -0.1),
                    ("h_min", 0.0),
                    ("delta", 0.3),
                ],
            );
            if rng.random_bool(0.7) {
                case.bounds = (1, n);
            }
            (case, params)
        })
        .collect()
}

/// Multi-sample chunks for `contact`'s step 4 (execute through a release the samples agree on):
/// `S` = 1..=8 samples whose gripper (the last dimension) is closed or open at action 0 and
/// opens, or not, at a random action — now and then exactly 0 or NaN — with speeds around
/// `slow`; parameters `release` and `quorum` around the chunk's and the samples' counts, or one
/// of them invalid.
fn contact_release_inputs(seed: u64, count: usize) -> Vec<(HorizonCase, PolicyParams)> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..count)
        .map(|i| {
            let dims = (
                rng.random_range(1..=8),
                rng.random_range(1..=3),
                rng.random_range(1..=16),
                rng.random_range(1..=4),
            );
            let (samples, _, n, d) = dims;
            let mut case = horizon_case(
                &mut rng,
                format!("release case {i}"),
                "random",
                dims,
                UpdateShape::Realistic,
            );
            let slow: f64 = rng.random_range(0.0..1.0);
            for s in 0..samples {
                let closed = rng.random_bool(0.7);
                let opens = rng.random_range(1..=n + 2);
                for action in 0..n {
                    let row = &mut case.actions[(s * n + action) * d..(s * n + action + 1) * d];
                    let speed = slow * rng.random_range(0.2..1.5);
                    for x in row[..d - 1].iter_mut() {
                        *x = speed as f32;
                    }
                    row[d - 1] = match rng.random_range(0..40) {
                        0 => 0.0,
                        1 => f32::NAN,
                        _ if closed && action < opens => 1.0,
                        _ => -1.0,
                    };
                }
            }
            let mut params = PolicyParams::new();
            params.insert("slow".into(), slow);
            params.insert("margin".into(), rng.random_range(0..=2) as f64);
            match rng.random_range(0..10) {
                0 => {
                    params.insert("release".into(), 0.0);
                }
                1 => {
                    params.insert("release".into(), 2.0);
                    params.insert("quorum".into(), 1.5);
                }
                2 => {
                    params.insert("quorum".into(), 2.0);
                }
                _ => {
                    params.insert("release".into(), rng.random_range(1..=n + 2) as f64);
                    if rng.random_bool(0.8) {
                        params.insert("quorum".into(), rng.random_range(1..=samples + 1) as f64);
                    }
                    if rng.random_bool(0.3) {
                        params.insert("h_max".into(), rng.random_range(1..=n + 2) as f64);
                    }
                }
            }
            if rng.random_bool(0.7) {
                case.bounds = (1, n);
            }
            (case, params)
        })
        .collect()
}

#[test]
fn contact_plugin_matches_its_native_twin() {
    let release = contact_release_inputs(29, 600);
    // Step 4 decides often enough that a twin ignoring it would fail: the answer with
    // `release` differs from the one without in many cases.
    let raised = release
        .iter()
        .filter(|(case, params)| {
            let mut without = params.clone();
            without.remove("release");
            without.remove("quorum");
            let mut native = ContactAware::default();
            let with = native.choose(&case.input(params));
            with.is_ok() && with != native.choose(&case.input(&without))
        })
        .count();
    assert!(raised > 50, "the release raised only {raised} answers");
    let mut inputs = contact_inputs(23, 600);
    inputs.extend(release);
    assert_twins("contact", &mut ContactAware::default(), inputs);
}

/// Pending lists with many ties: arrival times, waits and executions drawn from small sets, so
/// every tie-break rule of every policy is exercised.
fn pending_list(rng: &mut StdRng, len: usize) -> (Timestamp, Vec<PendingView>) {
    let now_us: u64 = rng.random_range(2_000_000..600_000_000);
    let coarse = rng.random_bool(0.5);
    let pick = |rng: &mut StdRng, max: u64| -> u64 {
        if coarse {
            [0, max / 4, max / 2, max][rng.random_range(0..4)]
        } else {
            rng.random_range(0..=max)
        }
    };
    let mut ids: Vec<u64> = (0..len as u64)
        .map(|i| i * 3 + rng.random_range(0..3))
        .collect();
    ids.reverse();
    let pending = (0..len)
        .map(|i| {
            let start = pick(rng, now_us);
            let life = now_us - start;
            let arrived = start + pick(rng, life);
            let ns = |rng: &mut StdRng, max_us: u64| {
                Duration::from_nanos(pick(rng, max_us) * 1000 + rng.random_range(0..1000))
            };
            PendingView {
                request: RequestId(ids[i]),
                task: TaskId(rng.random_range(0..50)),
                round_index: rng.random_range(0..100),
                arrived_at: Timestamp::from_micros(arrived),
                task_started_at: Timestamp::from_micros(start),
                skipped: [0, 0, 1, 3, 4, 9, 40][rng.random_range(0..7)],
                wait: ns(rng, life),
                attained_service: ns(rng, 30_000_000),
                queued: ns(rng, life),
                last_exec: rng.random_bool(0.8).then(|| ns(rng, 3_000_000)),
                exec_ends_at: rng.random_bool(0.8).then(|| {
                    Timestamp::from_micros(arrived + pick(rng, now_us + 3_000_000 - arrived))
                }),
                last_gen: rng.random_bool(0.8).then(|| ns(rng, 1_000_000)),
                rounds_completed: rng.random_range(0..100),
                remaining: rng.random_bool(0.2).then(|| RemainingWork {
                    rounds: Some(rng.random_range(0..50)),
                    seconds: None,
                }),
            }
        })
        .collect();
    (Timestamp::from_micros(now_us), pending)
}

/// Loads the priority plugin `name` with `params`, with a fallback that must never answer.
fn priority_plugin(
    name: &str,
    params: &[(&str, f64)],
) -> Result<WasmPriorityPolicy, kairos_server::plugin::LoadError> {
    let params: PolicyParams = params.iter().map(|(k, v)| (k.to_string(), *v)).collect();
    WasmPriorityPolicy::load(
        &PluginSource::File(shipped_plugin(name)),
        &params,
        options(PluginOptions::priority()),
        Box::new(Unreachable),
    )
}

/// Compares a priority plugin with the native policy `spec` on `decisions` random lists.
fn compare_priority(
    plugin_name: &str,
    spec: &str,
    params: &[(&str, f64)],
    decisions: usize,
    max_len: usize,
    seed: u64,
) {
    let mut plugin =
        priority_plugin(plugin_name, params).unwrap_or_else(|e| panic!("{plugin_name}: {e}"));
    let mut native = build_policy(&spec.parse::<PolicySpec>().unwrap()).unwrap();
    let mut rng = StdRng::seed_from_u64(seed);
    let (mut want, mut got) = (Vec::new(), Vec::new());
    for decision in 0..decisions {
        let len = if decision < 3 {
            decision
        } else {
            rng.random_range(0..=max_len)
        };
        let (now, pending) = pending_list(&mut rng, len);
        want.clear();
        native.order(now, &pending, &mut want).unwrap();
        plugin
            .call_plugin(now, &pending, &mut got)
            .unwrap_or_else(|f| panic!("{plugin_name} ({spec}) decision {decision}: {f}"));
        assert_eq!(
            got, want,
            "{plugin_name} vs native {spec}, decision {decision} ({len} pending)"
        );
    }
}

#[test]
fn fifo_plugin_matches_its_native_twin() {
    compare_priority("fifo", "fifo", &[], 300, 300, 21);
}

/// The server still loads plugins built against `kairos:policy@0.1.0` (record-per-request
/// pending list, an explicit order) next to 0.2.0 ones (columns, sort keys).
#[test]
fn a_0_1_0_priority_plugin_still_loads_and_matches_its_native_twin() {
    let old = priority_plugin("fifo_v0_1", &[]).unwrap();
    assert_eq!(old.meta().version.to_string(), "0.1.0");
    let new = priority_plugin("fifo", &[]).unwrap();
    assert_eq!(new.meta().version.to_string(), "0.2.0");
    compare_priority("fifo_v0_1", "fifo", &[], 200, 300, 22);
}

/// `ê = |E_last| · (1 + skipped)` saturates at 2^64 − 1 µs in every twin, so absurd execution
/// times tie (and fall through to arrival order) identically.
#[test]
fn kairos_plugins_agree_when_the_execution_key_saturates() {
    let mut rng = StdRng::seed_from_u64(35);
    let (now, mut pending) = pending_list(&mut rng, 64);
    for (i, p) in pending.iter_mut().enumerate() {
        p.wait = Duration::ZERO;
        // Nanoseconds near u64::MAX (what the WIT carries exactly); with these skip counts
        // (all in the top bucket by aging but the first) most products saturate.
        p.skipped = [0, 999, 5_000, u32::MAX][i % 4];
        p.last_exec = Some(Duration::from_nanos(u64::MAX - i as u64));
    }
    let mut native = build_policy(&"kairos".parse::<PolicySpec>().unwrap()).unwrap();
    let mut want = Vec::new();
    native.order(now, &pending, &mut want).unwrap();
    for name in ["kairos", "kairos_py"] {
        let mut got = Vec::new();
        priority_plugin(name, &[])
            .unwrap()
            .call_plugin(now, &pending, &mut got)
            .unwrap();
        assert_eq!(got, want, "{name}");
    }
}

#[test]
fn plas_plugin_matches_its_native_twin() {
    compare_priority("plas", "plas", &[], 200, 300, 22);
    compare_priority(
        "plas",
        "plas:queues=4,quantum_ms=0.25,growth=3,beta=2",
        &[
            ("queues", 4.0),
            ("quantum_ms", 0.25),
            ("growth", 3.0),
            ("beta", 2.0),
        ],
        200,
        300,
        23,
    );
    compare_priority("plas", "plas:queues=1", &[("queues", 1.0)], 50, 100, 24);
}

#[test]
fn kairos_plugin_matches_its_native_twin() {
    compare_priority("kairos", "kairos", &[], 200, 300, 31);
    compare_priority(
        "kairos",
        "kairos:buckets=inf",
        &[("buckets", f64::INFINITY)],
        200,
        300,
        32,
    );
    compare_priority(
        "kairos",
        "kairos:buckets=3,aging=2,intra=fifo",
        &[("buckets", 3.0), ("aging", 2.0), ("intra_fifo", 1.0)],
        200,
        300,
        33,
    );
}

#[test]
fn python_kairos_plugin_matches_its_native_twin() {
    compare_priority("kairos_py", "kairos", &[], 60, 200, 41);
    compare_priority(
        "kairos_py",
        "kairos:buckets=inf",
        &[("buckets", f64::INFINITY)],
        30,
        200,
        42,
    );
    compare_priority(
        "kairos_py",
        "kairos:buckets=3,aging=2,intra=fifo",
        &[("buckets", 3.0), ("aging", 2.0), ("intra_fifo", 1.0)],
        30,
        200,
        43,
    );
}

/// [`pending_list`] reshaped for SRW: deadlines before, at and after `now` (so both due and
/// not-due requests), and remaining-work hints of every shape, including the ones SRW must
/// ignore (seconds without a last execution, a zero execution, negative or non-finite seconds).
fn srw_pending_list(rng: &mut StdRng, len: usize) -> (Timestamp, Vec<PendingView>) {
    let (now, mut pending) = pending_list(rng, len);
    for view in &mut pending {
        match rng.random_range(0..10) {
            0 => view.exec_ends_at = Some(now),
            1 => view.exec_ends_at = None,
            2 => view.last_exec = Some(Duration::ZERO),
            _ => {}
        }
        view.remaining = match rng.random_range(0..10) {
            0..4 => None,
            4 => Some(RemainingWork {
                rounds: None,
                seconds: None,
            }),
            5 | 6 => Some(RemainingWork {
                rounds: Some([0, 1, 2, 5, rng.random_range(0..80)][rng.random_range(0..5)]),
                seconds: rng.random_bool(0.5).then(|| rng.random_range(0.0..30.0)),
            }),
            _ => Some(RemainingWork {
                rounds: None,
                seconds: Some(
                    [
                        rng.random_range(0.0..30.0),
                        0.25,
                        0.0,
                        -1.0,
                        f32::NAN,
                        f32::INFINITY,
                        1e-30,
                    ][rng.random_range(0..7)],
                ),
            }),
        };
    }
    (now, pending)
}

/// What a run of [`compare_srw`] exercised, for the caller's assertions.
struct SrwCoverage {
    /// Pending requests that were due / not due at their decision.
    due: usize,
    not_due: usize,
    /// Tasks reported finished to both twins (round count 0 included).
    finished: usize,
    /// Decisions whose order differed from that of an SRW that never learned anything: the
    /// learned Gittins index decided them.
    learned_decisions: usize,
}

/// Compares the SRW plugin with the native policy `spec` decision after decision, telling both
/// the same finished tasks in between so the plugin's Gittins index must track the native one.
fn compare_srw(
    spec: &str,
    params: &[(&str, f64)],
    decisions: usize,
    max_len: usize,
    seed: u64,
) -> SrwCoverage {
    let mut plugin = priority_plugin("srw", params).unwrap_or_else(|e| panic!("srw: {e}"));
    let spec: PolicySpec = spec.parse().unwrap();
    let mut native = build_policy(&spec).unwrap();
    let mut untrained = build_policy(&spec).unwrap();
    let slack = spec.params.get("slack").is_none_or(|s| s != "0");
    let mut rng = StdRng::seed_from_u64(seed);
    let mut coverage = SrwCoverage {
        due: 0,
        not_due: 0,
        finished: 0,
        learned_decisions: 0,
    };
    let (mut want, mut got, mut baseline) = (Vec::new(), Vec::new(), Vec::new());
    for decision in 0..decisions {
        for _ in 0..rng.random_range(0..=3) {
            let summary = FinishedTask {
                task: TaskId(rng.random()),
                rounds: [0, 1, 2, rng.random_range(1..=30), rng.random_range(1..=120)]
                    [rng.random_range(0..5)],
                latency: Duration::from_millis(rng.random_range(0..100_000)),
                attained_service: Duration::from_millis(rng.random_range(0..10_000)),
                wait: Duration::from_millis(rng.random_range(0..10_000)),
            };
            native.task_finished(&summary);
            plugin
                .call_task_finished(&summary)
                .unwrap_or_else(|f| panic!("srw ({spec}) task-finished: {f}"));
            coverage.finished += 1;
        }
        let len = if decision < 3 {
            decision
        } else {
            rng.random_range(0..=max_len)
        };
        let (now, pending) = srw_pending_list(&mut rng, len);
        want.clear();
        native.order(now, &pending, &mut want).unwrap();
        plugin
            .call_plugin(now, &pending, &mut got)
            .unwrap_or_else(|f| panic!("srw ({spec}) decision {decision}: {f}"));
        assert_eq!(
            got, want,
            "srw vs native {spec}, decision {decision} ({len} pending, {} tasks finished)",
            coverage.finished
        );
        baseline.clear();
        untrained.order(now, &pending, &mut baseline).unwrap();
        coverage.learned_decisions += usize::from(baseline != want);
        let due = pending
            .iter()
            .filter(|v| !slack || v.exec_ends_at.unwrap_or(v.arrived_at) <= now)
            .count();
        coverage.due += due;
        coverage.not_due += len - due;
    }
    coverage
}

#[test]
fn srw_plugin_matches_its_native_twin_while_both_learn() {
    // Default parameters: hints used, the learned index from the 21st finished task on.
    let c = compare_srw("srw", &[], 300, 200, 51);
    assert!(
        c.due > 1_000 && c.not_due > 1_000,
        "{} / {}",
        c.due,
        c.not_due
    );
    assert!(c.finished > 300, "{}", c.finished);
    assert!(
        c.learned_decisions > 100,
        "the learned index decided only {} of 300 decisions",
        c.learned_decisions
    );
    // Hints ignored: every due request is ordered by the learned index once warmed up.
    let c = compare_srw(
        "srw:hints=0,warmup=5",
        &[("hints", 0.0), ("warmup", 5.0)],
        200,
        200,
        52,
    );
    assert!(c.learned_decisions > 100, "{}", c.learned_decisions);
    // No warm-up: the index is read (empty, then tiny) from the first decision.
    let c = compare_srw(
        "srw:warmup=0,hints=0",
        &[("warmup", 0.0), ("hints", 0.0)],
        100,
        100,
        53,
    );
    assert!(c.learned_decisions > 50, "{}", c.learned_decisions);
    // Ablations: no slack (everything due, by work), deadline order among due requests.
    let c = compare_srw("srw:slack=0", &[("slack", 0.0)], 150, 200, 54);
    assert_eq!(c.not_due, 0);
    assert!(c.learned_decisions > 50, "{}", c.learned_decisions);
    compare_srw(
        "srw:due_order=deadline",
        &[("due_order", 1.0)],
        150,
        200,
        55,
    );
    compare_srw(
        "srw:slack=0,due_order=deadline,hints=0",
        &[("slack", 0.0), ("due_order", 1.0), ("hints", 0.0)],
        100,
        200,
        56,
    );
}

/// Seconds hints are converted with `Duration::as_secs_f64` (whole seconds and nanoseconds
/// converted separately), which for some executions of 1–2 s differs by an ulp from
/// `ns / 1e9`. Each decision pits such an execution against one half as long with half the
/// seconds: under `ns / 1e9` both requests would score the same and tie on arrival, but the
/// native scores differ, and the later arrival is placed first.
#[test]
fn srw_plugin_converts_seconds_hints_like_duration_as_secs_f64() {
    let mut plugin = priority_plugin("srw", &[]).unwrap();
    let mut native = build_policy(&PolicySpec::named("srw")).unwrap();
    let urgency = |exec_s: f64| 1.0 / (10.0 / exec_s).max(1.0);
    let now = Timestamp::from_micros(10_000_000);
    let view = |request: u64, arrived_us: u64, exec_ns: u64, seconds: f32| PendingView {
        request: RequestId(request),
        task: TaskId(request),
        round_index: 1,
        arrived_at: Timestamp::from_micros(arrived_us),
        task_started_at: Timestamp::from_micros(1_000),
        skipped: 0,
        wait: Duration::ZERO,
        attained_service: Duration::ZERO,
        queued: Duration::ZERO,
        last_exec: Some(Duration::from_nanos(exec_ns)),
        exec_ends_at: None,
        last_gen: None,
        rounds_completed: 1,
        remaining: Some(RemainingWork {
            rounds: None,
            seconds: Some(seconds),
        }),
    };
    let mut rng = StdRng::seed_from_u64(57);
    let (mut want, mut got, mut edges) = (Vec::new(), Vec::new(), 0);
    while edges < 100 {
        let ns = rng.random_range(500_000_000u64..1_000_000_000) * 2;
        let exact = Duration::from_nanos(ns).as_secs_f64();
        if urgency(exact) == urgency(ns as f64 / 1e9) {
            continue;
        }
        edges += 1;
        // Request 1 runs `ns`, request 2 half of it with half the work: the same rounds up to
        // the conversion. The one the native policy scores lower arrives first.
        let long_first = urgency(exact) < urgency(ns as f64 / 1e9);
        let (long_at, short_at) = if long_first { (1, 2) } else { (2, 1) };
        let pending = [view(1, long_at, ns, 10.0), view(2, short_at, ns / 2, 5.0)];
        want.clear();
        native.order(now, &pending, &mut want).unwrap();
        assert_eq!(want, [1, 0].map(|i| if long_first { i } else { 1 - i }));
        plugin.call_plugin(now, &pending, &mut got).unwrap();
        assert_eq!(got, want, "|E_last| = {ns} ns");
    }
}

#[test]
fn plugins_refuse_parameters_their_twins_refuse() {
    let load = |name: &str, params: &[(&str, f64)]| {
        priority_plugin(name, params).err().map(|e| e.to_string())
    };
    for (name, params, spec) in [
        ("fifo", &[("x", 1.0)][..], "fifo:x=1"),
        ("plas", &[("queues", 0.0)][..], "plas:queues=0"),
        ("plas", &[("beta", -1.0)][..], "plas:beta=-1"),
        ("kairos", &[("buckets", 0.0)][..], "kairos:buckets=0"),
        ("kairos", &[("aging", 1.5)][..], "kairos:aging=1.5"),
        ("kairos_py", &[("bucket", 3.0)][..], "kairos:bucket=3"),
        ("srw", &[("hint", 1.0)][..], "srw:hint=1"),
        ("srw", &[("hints", 2.0)][..], "srw:hints=2"),
        ("srw", &[("warmup", 2.5)][..], "srw:warmup=2.5"),
        ("srw", &[("due_order", 2.0)][..], "srw:due_order=2"),
    ] {
        assert!(
            build_policy(&spec.parse::<PolicySpec>().unwrap()).is_err(),
            "native accepts {spec}"
        );
        let refused = load(name, params).unwrap_or_else(|| panic!("{name} accepted {params:?}"));
        assert!(refused.contains("parameters"), "{refused}");
    }
}

/// The Python plugin runs inside deny-all WASI on its own worker thread; a deadline shorter
/// than its call interrupts the Python interpreter mid-sort, and the next call works again.
#[test]
fn a_python_plugin_is_interrupted_at_its_deadline_and_recovers() {
    let mut plugin = WasmPriorityPolicy::load(
        &PluginSource::File(shipped_plugin("kairos_py")),
        &PolicyParams::new(),
        PluginOptions {
            deadline: Duration::from_millis(10),
            quarantine_after: 100,
            ..options(PluginOptions::priority())
        },
        build_policy(&"fifo".parse::<PolicySpec>().unwrap()).unwrap(),
    )
    .unwrap();
    assert!(plugin.meta().info.imports_wasi);
    let mut rng = StdRng::seed_from_u64(5);
    let (now, big) = pending_list(&mut rng, 20_000);
    let mut order = Vec::new();
    // That the call returned and counted a timeout shows the interrupt worked; how long past
    // its deadline it returned is load-dependent and not asserted (plugin benchmarks measure it).
    plugin.order(now, &big, &mut order).unwrap();
    assert_eq!(
        plugin.stats().failures_of(FailureKind::Timeout),
        1,
        "{:?}",
        plugin.stats()
    );
    let mut fifo = Vec::new();
    build_policy(&"fifo".parse::<PolicySpec>().unwrap())
        .unwrap()
        .order(now, &big, &mut fifo)
        .unwrap();
    assert_eq!(
        order, fifo,
        "the fallback (fifo) ordered the interrupted decision"
    );

    let (now, small) = pending_list(&mut rng, 5);
    let mut native = build_policy(&"kairos".parse::<PolicySpec>().unwrap()).unwrap();
    let mut want = Vec::new();
    native.order(now, &small, &mut want).unwrap();
    plugin.order(now, &small, &mut order).unwrap();
    assert_eq!(order, want, "a fresh instance answers the next decision");
    assert_eq!(plugin.stats().answered, 1);
}
