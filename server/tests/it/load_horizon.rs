//! The load-aware horizon (`kairos:policy@0.3.0`, issue #14 §3): its C plugin gives exactly the
//! native policy's answer with and without a server load, and plugins built for 0.1.0/0.2.0
//! (which cannot see the load) still load and answer as their native twins, whatever the load.
//! Run `plugins/build.sh` first (CI does); a missing plugin fails the test.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::time::Duration;

use kairos_core::horizon::load_aware::LoadAware;
use kairos_core::horizon::threshold::Threshold;
use kairos_core::horizon::{HorizonPolicy, PolicyParams};
use kairos_core::scheduler::ServerLoad;
use kairos_server::plugin::conformance::horizon_cases;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::plugin_common::{horizon_plugin, same_answer};

/// A load whose backlog lasts about `actions` actions at `hz`, give or take a fraction (so the
/// ceiling is exercised), or none.
fn load_lasting(rng: &mut StdRng, actions: u32, hz: f32) -> Option<ServerLoad> {
    (actions > 0).then(|| ServerLoad {
        queued: rng.random_range(0..64),
        running: rng.random_range(0..32),
        open_tasks: rng.random_range(0..200),
        backlog: Duration::try_from_secs_f64(
            (f64::from(actions) - rng.random_range(0.0..1.0)) / f64::from(hz),
        )
        .expect("a positive backlog of a few seconds"),
    })
}

#[test]
fn load_aware_plugin_matches_its_native_twin() {
    let mut wasm = horizon_plugin("load_aware");
    assert_eq!(wasm.meta().version.to_string(), "0.3.0");
    let mut rng = StdRng::seed_from_u64(21);
    let (mut decided, mut lengthened) = (0, 0);
    for mut case in horizon_cases(9, 600) {
        let n = case.dims.2 as u32;
        // Half the cases keep the suite's random load (none, idle, deep queues, seconds of
        // backlog); the others a backlog of a few actions, where the ceiling decides.
        if rng.random_bool(0.5) {
            let actions = rng.random_range(0..=n.min(20));
            case.load = load_lasting(&mut rng, actions, case.control_hz);
        }
        let mut params = PolicyParams::new();
        match rng.random_range(0..10) {
            0 => {
                params.insert("gain".into(), -1.0);
            }
            1 => {
                params.insert("bogus".into(), 1.0);
            }
            2..=5 => {
                params.insert(
                    "gain".into(),
                    [0.0, 0.5, 1.0, 2.0, 3.7][rng.random_range(0..5)],
                );
                params.insert("t".into(), rng.random_range(0.0..1.0));
            }
            6 => {
                params.insert("h_min".into(), rng.random_range(1..=n) as f64);
            }
            _ => {}
        }
        let input = case.input(&params);
        let want = match LoadAware::from_params(&params) {
            Ok(mut native) => native.choose(&input),
            Err(e) => Err(e),
        };
        let (got, _) = wasm
            .call_plugin(&input)
            .unwrap_or_else(|f| panic!("{}: {f}", case.name));
        assert!(
            same_answer(&want, &got),
            "{}: native {want:?}, plugin {got:?}, params {params:?}, load {:?}",
            case.name,
            case.load
        );
        if let Ok(h) = want {
            decided += 1;
            // The threshold rule with the same `t` and `h_min`, on the same chunk.
            let base: PolicyParams = params
                .iter()
                .filter(|(k, _)| k.as_str() != "gain")
                .map(|(k, v)| (k.clone(), *v))
                .collect();
            let threshold = Threshold::default().choose(&case.input(&base)).unwrap();
            assert!(
                h >= threshold,
                "{}: shorter than the threshold rule",
                case.name
            );
            lengthened += usize::from(h > threshold);
        }
    }
    assert!(decided > 375, "too few valid decisions: {decided}");
    assert!(
        lengthened > 50,
        "the load lengthened too few horizons to compare the load path: {lengthened}"
    );
}

#[test]
fn plugins_of_older_versions_ignore_the_load_and_answer_as_before() {
    // threshold.wasm is built for 0.2.0, fifo_v0_1.wasm for 0.1.0 (the latter's loading and
    // answers are checked in plugin_twins). A 0.2.0 horizon plugin cannot see the load: its
    // answer is the native threshold rule's with or without one.
    let mut wasm = horizon_plugin("threshold");
    assert_eq!(wasm.meta().version.to_string(), "0.2.0");
    let mut native = Threshold::default();
    let mut rng = StdRng::seed_from_u64(22);
    let params = PolicyParams::new();
    for mut case in horizon_cases(10, 100) {
        let mut answers = Vec::new();
        for load in [None, load_lasting(&mut rng, 40, case.control_hz)] {
            case.load = load;
            let input = case.input(&params);
            let (got, _) = wasm
                .call_plugin(&input)
                .unwrap_or_else(|f| panic!("{}: {f}", case.name));
            assert!(same_answer(&native.choose(&input), &got), "{}", case.name);
            answers.push(got);
        }
        assert_eq!(
            answers[0], answers[1],
            "{}: the load changed a 0.2.0 answer",
            case.name
        );
    }
}
