//! Hostile plugins are contained: each is stopped (a call that returns at all was contained: an
//! uncontained loop never returns) for the reason its fixture provokes (deadline, memory cap,
//! trap, invalid answer), its instance is discarded, the decision is answered by the fallback
//! policy, and every robot request still gets a valid answer. Plugins for the wrong world, version or imports are
//! refused at load with a clear error.

use std::time::{Duration, Instant};

use crate::plugin_common::*;
use kairos_core::horizon::{
    ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams, validate_horizon,
};
use kairos_core::scheduler::{
    FinishedTask, PendingView, PolicyError, PriorityPolicy, RequestId, TaskId, validate_order,
};
use kairos_core::time::Timestamp;
use kairos_server::plugin::cache::{CodeCache, CodeSource};
use kairos_server::plugin::inspect::InspectError;
use kairos_server::plugin::{
    FailureKind, LoadError, PluginKind, PluginOptions, PluginSource, WasmHorizonPolicy,
    WasmPriorityPolicy,
};

// No upper bounds on how long a contained call took: a loaded machine can stretch any wall-clock
// margin. That a call returns proves containment (the loop fixtures never would); the failure
// kind recorded proves which mechanism stopped it. Lower bounds (a deadline is not cut short)
// are safe: load only makes calls longer. How fast containment is lives in the plugin
// benchmarks (docs/BENCHMARKS.md).

/// The fallback of these tests: always `h_min`, recognisable in the answers.
struct MinHorizon;

impl HorizonPolicy for MinHorizon {
    fn name(&self) -> &str {
        "min"
    }
    fn choose(&mut self, input: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        Ok(input.h_min)
    }
}

/// The priority fallback of these tests: reverse list order, recognisable in the answers.
struct Reverse;

impl PriorityPolicy for Reverse {
    fn name(&self) -> &str {
        "reverse"
    }
    fn order(
        &mut self,
        _: Timestamp,
        pending: &[PendingView],
        order: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        order.extend((0..pending.len()).rev());
        Ok(())
    }
}

struct Chunk {
    updates: Vec<f32>,
    actions: Vec<f32>,
    params: PolicyParams,
}

impl Chunk {
    /// A 1×10×50×7 chunk.
    fn new() -> Self {
        Chunk {
            updates: (0..10 * 50 * 7).map(|i| (i % 13) as f32 * 0.01).collect(),
            actions: vec![0.5; 50 * 7],
            params: PolicyParams::new(),
        }
    }

    fn input(&self, h_min: usize, h_max: usize, round: u64) -> HorizonInput<'_> {
        HorizonInput {
            chunk: ChunkView {
                samples: 1,
                steps: 10,
                chunk_len: 50,
                action_dim: 7,
                updates: &self.updates,
                actions: &self.actions,
            },
            h_min,
            h_max,
            control_hz: 30.0,
            round_index: round,
            recent_horizons: &[],
            params: &self.params,
            load: None,
        }
    }
}

fn horizon_plugin(wasm: Vec<u8>, options: PluginOptions) -> WasmHorizonPolicy {
    WasmHorizonPolicy::load(
        &PluginSource::Bytes {
            name: "fixture".into(),
            wasm,
        },
        options,
        Box::new(MinHorizon),
    )
    .expect("fixture loads")
}

fn priority_plugin(wasm: Vec<u8>, options: PluginOptions) -> WasmPriorityPolicy {
    WasmPriorityPolicy::load(
        &PluginSource::Bytes {
            name: "fixture".into(),
            wasm,
        },
        &PolicyParams::new(),
        options,
        Box::new(Reverse),
    )
    .expect("fixture loads")
}

fn pending(n: usize) -> Vec<PendingView> {
    (0..n)
        .map(|i| PendingView {
            request: RequestId(i as u64),
            task: TaskId(i as u64),
            round_index: 3,
            arrived_at: Timestamp::from_micros(1_000 + i as u64),
            task_started_at: Timestamp::from_micros(10),
            skipped: 0,
            wait: Duration::from_micros(400),
            attained_service: Duration::from_micros(300),
            queued: Duration::from_micros(100),
            last_exec: Some(Duration::from_millis(200)),
            exec_ends_at: Some(Timestamp::from_micros(1_500 + i as u64)),
            last_gen: Some(Duration::from_millis(80)),
            rounds_completed: 3,
            remaining: None,
        })
        .collect()
}

fn horizon_options(deadline_ms: u64) -> PluginOptions {
    PluginOptions {
        deadline: Duration::from_millis(deadline_ms),
        memory_limit: 8 << 20,
        ..PluginOptions::horizon()
    }
}

#[test]
fn a_well_behaved_fixture_answers_through_the_plugin() {
    let chunk = Chunk::new();
    let mut policy = horizon_plugin(horizon_component(HORIZON_H_MAX), horizon_options(50));
    assert_eq!(policy.meta().kind, PluginKind::Horizon);
    assert_eq!(policy.meta().version.to_string(), "0.1.0");
    for round in 0..20 {
        assert_eq!(policy.choose(&chunk.input(3, 40, round)), Ok(40));
    }
    let stats = policy.stats();
    assert_eq!((stats.answered, stats.fallbacks), (20, 0));
    assert!(stats.failures.is_empty(), "{stats:?}");
}

#[test]
fn an_infinite_loop_is_interrupted_at_its_deadline() {
    let chunk = Chunk::new();
    let deadline = Duration::from_millis(20);
    let mut policy = horizon_plugin(horizon_component(HORIZON_LOOP), horizon_options(20));
    let started = Instant::now();
    let answer = policy.choose(&chunk.input(4, 30, 0));
    let took = started.elapsed();
    assert_eq!(answer, Ok(4), "the fallback (h_min) answers");
    assert!(took >= deadline, "cut short: {took:?} < {deadline:?}");
    let stats = policy.stats();
    assert_eq!(stats.failures_of(FailureKind::Timeout), 1, "{stats:?}");
    assert_eq!(
        stats.failures.len(),
        1,
        "stopped by its deadline only: {stats:?}"
    );
}

#[test]
fn a_memory_hog_is_stopped_at_its_cap() {
    let chunk = Chunk::new();
    let mut policy = horizon_plugin(horizon_component(HORIZON_HOG), horizon_options(1_000));
    assert_eq!(policy.choose(&chunk.input(5, 30, 0)), Ok(5));
    // Stopped by the limiter, not by the 1 s deadline.
    let stats = policy.stats();
    assert_eq!(stats.failures_of(FailureKind::OverLimit), 1, "{stats:?}");
    assert_eq!(stats.failures_of(FailureKind::Timeout), 0, "{stats:?}");
    assert!(policy.peak_memory() <= 8 << 20);
}

#[test]
fn a_trap_discards_the_instance_and_the_next_call_gets_a_fresh_one() {
    let chunk = Chunk::new();
    // Traps on odd rounds, answers h_max on even ones.
    let body = "(if (i32.wrap_i64 (i64.and (local.get 11) (i64.const 1))) (then unreachable)) (local.get 9)";
    let mut policy = horizon_plugin(horizon_component(body), horizon_options(50));
    for round in 0..10u64 {
        let expected = if round % 2 == 1 { 2 } else { 20 };
        assert_eq!(
            policy.choose(&chunk.input(2, 20, round)),
            Ok(expected),
            "round {round}"
        );
    }
    let stats = policy.stats();
    assert_eq!(stats.failures_of(FailureKind::Trap), 5);
    assert_eq!(stats.answered, 5);
    assert!(
        !stats.quarantined,
        "a success between failures resets the streak"
    );
}

#[test]
fn invalid_horizons_are_rejected_and_fall_back() {
    let chunk = Chunk::new();
    for body in [HORIZON_TOO_LONG, HORIZON_ZERO] {
        let mut policy = horizon_plugin(horizon_component(body), horizon_options(50));
        assert_eq!(policy.choose(&chunk.input(6, 30, 0)), Ok(6), "{body}");
        assert_eq!(policy.stats().failures_of(FailureKind::InvalidAnswer), 1);
        let direct = policy.call_plugin(&chunk.input(6, 30, 0));
        assert_eq!(
            direct.map(|_| ()).map_err(|f| f.kind),
            Err(FailureKind::InvalidAnswer)
        );
    }
}

#[test]
fn a_plugin_that_keeps_failing_is_quarantined_and_costs_nothing_meanwhile() {
    let chunk = Chunk::new();
    let options = PluginOptions {
        quarantine_after: 3,
        probation: 50,
        ..horizon_options(10)
    };
    let mut policy = horizon_plugin(horizon_component(HORIZON_LOOP), options);
    for round in 0..3 {
        assert_eq!(policy.choose(&chunk.input(1, 50, round)), Ok(1));
    }
    assert!(policy.stats().quarantined);
    for round in 3..53 {
        assert_eq!(policy.choose(&chunk.input(1, 50, round)), Ok(1));
    }
    // 50 decisions sat out: none called the plugin (no new timeout), so none paid the 10 ms
    // deadline.
    let stats = policy.stats();
    assert_eq!(stats.failures_of(FailureKind::Timeout), 3);
    assert_eq!(stats.failures_of(FailureKind::Quarantined), 50);
    // The next decision probes it again, fails, and doubles the quarantine.
    assert_eq!(policy.choose(&chunk.input(1, 50, 99)), Ok(1));
    let stats = policy.stats();
    assert_eq!(stats.failures_of(FailureKind::Timeout), 4);
    assert_eq!(stats.quarantines, 2);
}

/// Many robots, every hostile horizon plugin: every request gets an executable horizon, and
/// the whole run stays far below what one uncontained call would cost (forever).
#[test]
fn every_robot_request_is_answered_whatever_the_horizon_plugin_does() {
    let chunk = Chunk::new();
    for (name, body) in [
        ("loop", HORIZON_LOOP),
        ("hog", HORIZON_HOG),
        ("trap", HORIZON_TRAP),
        ("too long", HORIZON_TOO_LONG),
        ("zero", HORIZON_ZERO),
    ] {
        let options = PluginOptions {
            quarantine_after: 3,
            probation: 100,
            ..horizon_options(5)
        };
        let mut policy = horizon_plugin(horizon_component(body), options);
        let robots = 40;
        let rounds = 10;
        for round in 0..rounds {
            for robot in 0..robots {
                let h_min = 1 + (robot % 7);
                let input = chunk.input(h_min, 50, round);
                let h = policy.choose(&input);
                assert_eq!(
                    h.and_then(|h| validate_horizon(h, &input)),
                    Ok(h_min),
                    "{name}: robot {robot} round {round}"
                );
            }
        }
        let stats = policy.stats();
        assert_eq!(stats.decisions, robots as u64 * rounds);
        assert_eq!(stats.fallbacks, stats.decisions, "{name}: {stats:?}");
        assert!(stats.quarantined, "{name}: {stats:?}");
        // Of 400 decisions only 5 called the plugin (so at most 5 paid a deadline): 3 failures
        // start a quarantine of 100 decisions, the probe after it fails and doubles it to 200,
        // the probe after that fails and doubles it to 400, which outlasts the run.
        let called = stats.decisions - stats.failures_of(FailureKind::Quarantined);
        assert_eq!((called, stats.quarantines), (5, 3), "{name}: {stats:?}");
    }
}

#[test]
fn hostile_priority_plugins_are_contained_and_every_request_is_ordered() {
    let deadline = Duration::from_millis(20);
    for (name, body, kind) in [
        ("loop", PRIORITY_LOOP, FailureKind::Timeout),
        ("hog", PRIORITY_HOG, FailureKind::OverLimit),
        ("trap", PRIORITY_TRAP, FailureKind::Trap),
        ("omit", PRIORITY_OMIT, FailureKind::InvalidAnswer),
        ("duplicate", PRIORITY_DUPLICATE, FailureKind::InvalidAnswer),
    ] {
        let options = PluginOptions {
            deadline,
            memory_limit: 8 << 20,
            ..PluginOptions::priority()
        };
        // The trial call at load uses an empty list, which the invalid-order fixtures pass.
        let wasm = priority_component(body);
        let load = WasmPriorityPolicy::load(
            &PluginSource::Bytes {
                name: name.into(),
                wasm,
            },
            &PolicyParams::new(),
            options,
            Box::new(Reverse),
        );
        let mut policy = match load {
            Ok(policy) => policy,
            // Loops, hogs and traps already fail the trial call: refused at load.
            Err(LoadError::Compile { message, .. }) => {
                assert!(
                    matches!(
                        kind,
                        FailureKind::Timeout | FailureKind::OverLimit | FailureKind::Trap
                    ),
                    "{name}: {message}"
                );
                assert!(message.contains(&kind.to_string()), "{name}: {message}");
                continue;
            }
            Err(e) => panic!("{name}: {e}"),
        };
        for decision in 0..20 {
            // At least two requests: a one-element "duplicate" order would be valid.
            let pending = pending(2 + decision * 7);
            let mut order = Vec::new();
            policy
                .order(Timestamp::from_micros(100_000), &pending, &mut order)
                .expect("a wrapped policy always orders");
            validate_order(pending.len(), &order).expect("complete order");
            let reverse: Vec<usize> = (0..pending.len()).rev().collect();
            assert_eq!(
                order, reverse,
                "{name}: the fallback ordered decision {decision}"
            );
        }
        let stats = policy.stats();
        assert!(stats.failures_of(kind) >= 1, "{name}: {stats:?}");
        assert_eq!(stats.fallbacks, 20, "{name}: {stats:?}");
    }
}

#[test]
fn hostile_priority_plugins_that_pass_the_load_check_are_contained_at_run_time() {
    // Well-behaved on an empty list (so they load), hostile on anything else.
    let guard = "(if (i32.eqz (local.get 2)) (then (return (i32.const 0))))";
    let empty_ok = |hostile: &str| format!("{guard} {hostile}");
    let deadline = Duration::from_millis(20);
    for (name, body, kind) in [
        ("loop", empty_ok(PRIORITY_LOOP), FailureKind::Timeout),
        ("hog", empty_ok(PRIORITY_HOG), FailureKind::OverLimit),
        ("trap", empty_ok(PRIORITY_TRAP), FailureKind::Trap),
    ] {
        let options = PluginOptions {
            deadline,
            memory_limit: 8 << 20,
            quarantine_after: 1_000,
            ..PluginOptions::priority()
        };
        let mut policy = priority_plugin(priority_component(&body), options);
        for decision in 0..5 {
            let pending = pending(10 + decision);
            let mut order = Vec::new();
            let started = Instant::now();
            policy
                .order(Timestamp::from_micros(100_000), &pending, &mut order)
                .expect("a wrapped policy always orders");
            let took = started.elapsed();
            if kind == FailureKind::Timeout {
                assert!(took >= deadline, "{name}: cut short at {took:?}");
            }
            validate_order(pending.len(), &order).expect("complete order");
        }
        assert_eq!(
            policy.stats().failures_of(kind),
            5,
            "{name}: {:?}",
            policy.stats()
        );
    }
}

#[test]
fn a_well_behaved_priority_fixture_orders_through_the_plugin() {
    let mut policy = priority_plugin(
        priority_component(PRIORITY_IDENTITY),
        PluginOptions::priority(),
    );
    for n in [0, 1, 5, 1000] {
        let mut order = Vec::new();
        policy
            .order(Timestamp::from_micros(5_000), &pending(n), &mut order)
            .expect("orders");
        assert_eq!(order, (0..n).collect::<Vec<_>>());
    }
    assert_eq!(policy.stats().fallbacks, 0);
}

fn load_error(wasm: Vec<u8>, kind: PluginKind) -> LoadError {
    let source = PluginSource::Bytes {
        name: "fixture".into(),
        wasm,
    };
    match kind {
        PluginKind::Horizon => {
            WasmHorizonPolicy::load(&source, PluginOptions::horizon(), Box::new(MinHorizon)).err()
        }
        PluginKind::Priority => WasmPriorityPolicy::load(
            &source,
            &PolicyParams::new(),
            PluginOptions::priority(),
            Box::new(Reverse),
        )
        .err(),
    }
    .expect("the fixture must be refused")
}

fn inspect_error(error: LoadError) -> InspectError {
    match error {
        LoadError::Inspect { source, .. } => source,
        other => panic!("expected an inspection error, got {other}"),
    }
}

#[test]
fn a_plugin_for_the_wrong_world_is_refused_at_load() {
    let error = load_error(priority_component(PRIORITY_IDENTITY), PluginKind::Horizon);
    let message = error.to_string();
    assert_eq!(
        inspect_error(error),
        InspectError::WrongWorld {
            expected: PluginKind::Horizon,
            found: PluginKind::Priority
        }
    );
    assert!(message.contains("is a priority plugin"), "{message}");

    let error = load_error(horizon_component(HORIZON_H_MIN), PluginKind::Priority);
    assert!(matches!(
        inspect_error(error),
        InspectError::WrongWorld { .. }
    ));
}

#[test]
fn a_plugin_for_an_unsupported_version_is_refused_at_load() {
    let wasm = foreign_component(
        &wit_with_version("0.9.0"),
        "horizon-policy",
        &horizon_wat(HORIZON_H_MIN).replace("@0.1.0", "@0.9.0"),
    );
    let error = load_error(wasm, PluginKind::Horizon);
    let message = error.to_string();
    assert!(matches!(
        inspect_error(error),
        InspectError::UnsupportedVersion { .. }
    ));
    assert!(
        message.contains("kairos:policy@0.9.0")
            && message.contains("supported: 0.1.0, 0.2.0, 0.3.0"),
        "{message}"
    );
}

#[test]
fn a_component_of_another_package_is_refused_at_load() {
    let wit = "package acme:other@1.0.0; interface thing { go: func() -> u32; } world w { export thing; }";
    let wat = r#"(module (memory (export "memory") 1) (func (export "acme:other/thing@1.0.0#go") (result i32) (i32.const 7)))"#;
    let error = load_error(foreign_component(wit, "w", wat), PluginKind::Horizon);
    let message = error.to_string();
    assert!(matches!(
        inspect_error(error),
        InspectError::NoPolicyExport { .. }
    ));
    assert!(message.contains("acme:other/thing@1.0.0"), "{message}");
}

#[test]
fn a_plugin_importing_a_capability_is_refused_at_load() {
    let wit = wit_with_version("0.1.0").replace(
        "world horizon-policy {\n    export horizon;",
        "interface net { connect: func(host: string) -> u32; }\nworld horizon-policy {\n    import net;\n    export horizon;",
    );
    let wat = horizon_wat(HORIZON_H_MIN).replace(
        "(module",
        r#"(module (import "kairos:policy/net@0.1.0" "connect" (func (param i32 i32) (result i32)))"#,
    );
    let error = load_error(
        foreign_component(&wit, "horizon-policy", &wat),
        PluginKind::Horizon,
    );
    let message = error.to_string();
    assert_eq!(
        inspect_error(error),
        InspectError::ForbiddenImport("kairos:policy/net@0.1.0".into())
    );
    assert!(message.contains("does not provide"), "{message}");
}

#[test]
fn a_core_module_or_garbage_is_refused_at_load() {
    let core = wat::parse_str(horizon_wat(HORIZON_H_MIN)).unwrap();
    let message = load_error(core, PluginKind::Horizon).to_string();
    assert!(
        message.contains("core module") && message.contains("componentize"),
        "{message}"
    );
    let error = load_error(b"not wasm at all".to_vec(), PluginKind::Horizon);
    assert!(matches!(
        inspect_error(error),
        InspectError::NotAComponent(_)
    ));
}

#[test]
fn the_code_cache_reuses_only_entries_the_server_wrote() {
    let dir = tempfile::tempdir().unwrap();
    let cache = CodeCache::open(dir.path().join("cache")).unwrap();
    let wasm = horizon_component(HORIZON_H_MAX);
    let options = PluginOptions {
        cache: Some(cache.clone()),
        ..PluginOptions::horizon()
    };
    let load = |options: &PluginOptions| {
        WasmHorizonPolicy::load(
            &PluginSource::Bytes {
                name: "cached".into(),
                wasm: wasm.clone(),
            },
            options.clone(),
            Box::new(MinHorizon),
        )
        .unwrap()
    };
    assert_eq!(load(&options).meta().code, CodeSource::Compiled);
    let mut cached = load(&options);
    assert_eq!(cached.meta().code, CodeSource::Cached);
    let chunk = Chunk::new();
    assert_eq!(cached.choose(&chunk.input(2, 33, 0)), Ok(33));

    // Replace the cached code with other (valid!) precompiled code: its tag no longer
    // verifies, so it is recompiled from the component, never deserialised.
    let entry = std::fs::read_dir(cache.dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "cwasm"))
        .expect("a cache entry");
    let engine = wasmtime::Engine::new(wasmtime::Config::new().epoch_interruption(true)).unwrap();
    let other = engine
        .precompile_component(&horizon_component(HORIZON_H_MIN))
        .unwrap();
    std::fs::write(&entry, other).unwrap();
    let mut recompiled = load(&options);
    assert_eq!(recompiled.meta().code, CodeSource::Compiled);
    assert_eq!(
        recompiled.choose(&chunk.input(2, 33, 0)),
        Ok(33),
        "the tampered code never ran"
    );

    // A second cache (another installation) does not trust the first one's entries.
    let stranger = CodeCache::open(dir.path().join("other")).unwrap();
    let tag = entry.with_extension("cwasm.mac");
    for file in [&entry, &tag] {
        std::fs::copy(file, stranger.dir().join(file.file_name().unwrap())).unwrap();
    }
    let options = PluginOptions {
        cache: Some(stranger),
        ..PluginOptions::horizon()
    };
    assert_eq!(load(&options).meta().code, CodeSource::Compiled);
}

#[test]
fn start_code_that_never_returns_is_interrupted_at_the_instantiation_deadline() {
    let chunk = Chunk::new();
    let wat = horizon_wat(HORIZON_H_MAX).replace(
        "(module",
        r#"(module (func (export "_initialize") (loop $spin (br $spin)))"#,
    );
    let options = PluginOptions {
        instantiate_deadline: Duration::from_millis(30),
        ..horizon_options(5)
    };
    let mut policy = horizon_plugin(component(&wat, PluginKind::Horizon), options);
    let started = Instant::now();
    assert_eq!(policy.choose(&chunk.input(3, 30, 0)), Ok(3));
    let took = started.elapsed();
    assert!(took >= Duration::from_millis(30), "cut short: {took:?}");
    let stats = policy.stats();
    assert_eq!(stats.failures_of(FailureKind::Instantiate), 1, "{stats:?}");
    assert_eq!(stats.failures.len(), 1, "{stats:?}");
}

#[test]
fn handles_of_one_plugin_share_health_and_warm_instances_across_threads() {
    let plugin = kairos_server::plugin::HorizonPlugin::load(
        &PluginSource::Bytes {
            name: "shared".into(),
            wasm: horizon_component(HORIZON_H_MAX),
        },
        horizon_options(100),
    )
    .unwrap();
    std::thread::scope(|scope| {
        for robot in 0..4u64 {
            let mut policy = plugin.policy(Box::new(MinHorizon));
            scope.spawn(move || {
                let chunk = Chunk::new();
                for round in 0..200 {
                    assert_eq!(
                        policy.choose(&chunk.input(1, 25, round)),
                        Ok(25),
                        "robot {robot}"
                    );
                }
            });
        }
    });
    let stats = plugin.stats();
    assert_eq!(
        (stats.decisions, stats.answered, stats.fallbacks),
        (800, 800, 0),
        "{stats:?}"
    );
}

/// What a plugin that never returns from one export did to its health after `calls` calls.
fn stuck_outcome(stats: &kairos_server::plugin::PluginStats) -> (u64, u64, bool) {
    (
        stats.failures_of(FailureKind::Timeout),
        stats.quarantines,
        stats.quarantined,
    )
}

#[test]
fn a_call_that_never_returns_is_handled_alike_in_every_export() {
    // Each export in turn loops forever; the others behave. Every such call goes through the
    // one call wrapper: interrupted at its deadline, its instance discarded, counted as a
    // timeout, and the plugin quarantined after `quarantine_after` of them, whichever export.
    let options = PluginOptions {
        quarantine_after: 3,
        ..horizon_options(5)
    };
    let chunk = Chunk::new();
    let mut choose = horizon_plugin(horizon_component(HORIZON_LOOP), options.clone());
    for round in 0..3 {
        assert_eq!(
            choose.choose(&chunk.input(2, 40, round)),
            Ok(2),
            "the fallback answers"
        );
    }
    let options = PluginOptions {
        deadline: Duration::from_millis(5),
        ..options
    };
    // `order` loops, but only on non-empty lists: the load's trial call (empty) passes.
    let order_loop =
        format!("(if (i32.eqz (local.get 2)) (then (return (i32.const 0)))) {PRIORITY_LOOP}");
    let mut order = priority_plugin(priority_component(&order_loop), options.clone());
    let pending = pending(4);
    for _ in 0..3 {
        let mut answer = Vec::new();
        order
            .order(Timestamp::from_micros(5_000), &pending, &mut answer)
            .unwrap();
        assert_eq!(answer, [3, 2, 1, 0], "the fallback orders");
    }
    let finished = FinishedTask {
        task: TaskId(1),
        rounds: 4,
        latency: Duration::from_secs(2),
        attained_service: Duration::from_millis(300),
        wait: Duration::from_millis(100),
    };
    let mut notified = priority_plugin(
        component(
            &priority_wat_notified(PRIORITY_IDENTITY, FINISHED_LOOP),
            PluginKind::Priority,
        ),
        options,
    );
    for _ in 0..3 {
        notified.task_finished(&finished);
    }
    // A quarantined plugin is not told either: nothing more is counted.
    notified.task_finished(&finished);
    for (export, stats) in [
        ("choose", choose.stats()),
        ("order", order.stats()),
        ("task-finished", notified.stats()),
    ] {
        assert_eq!(stuck_outcome(&stats), (3, 1, true), "{export}: {stats:?}");
    }
    // Decisions fell back; a notification has nothing to fall back for.
    assert_eq!((choose.stats().fallbacks, order.stats().fallbacks), (3, 3));
    assert_eq!(notified.stats().fallbacks, 0);
}
