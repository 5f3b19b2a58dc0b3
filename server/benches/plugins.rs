//! Per-call cost of each shipped plugin against its native twin, through the same trait the
//! server calls (`HorizonPolicy::choose`, `PriorityPolicy::order`), so the WASM numbers include
//! everything the server pays: converting the input, copying it into the sandbox, the epoch
//! deadline, validating the answer and the health bookkeeping.
//!
//! - Horizon (50×10×7 input, S=1): `threshold` on a realistic chunk and on a fully converged one
//!   (the scan covers all 50 actions: the worst case), `static`; plus `threshold` with a fresh
//!   instance per call (`InstanceMode::Fresh`) to show why instances are reused.
//! - Priority, 10 / 100 / 1,000 pending: `fifo`, `plas`, `kairos`, `srw` (C, WIT 0.2.0: columns
//!   in, sort keys out; `srw` trained on the same 200 finished tasks as its twin), `kairos` in
//!   Python, and `fifo` built against WIT 0.1.0 (a record per request in, an order out) as the
//!   baseline the 0.2.0 layout is measured against.
//!
//! Target (issue #4): the C plugins at most 3× their native twin.
//! Run `bash plugins/build.sh` first, then `cargo bench -p kairos-server --bench plugins`.

#![allow(clippy::unwrap_used)] // benches may unwrap, like tests (RULES.md)

use std::hint::black_box;
use std::path::PathBuf;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use kairos_core::horizon::fixed::StaticHorizon;
use kairos_core::horizon::threshold::Threshold;
use kairos_core::horizon::{HorizonError, HorizonInput, HorizonPolicy, PolicyParams};
use kairos_core::scheduler::{
    FinishedTask, PendingView, PolicyError, PolicySpec, PriorityPolicy, TaskId, build_policy,
};
use kairos_core::time::Timestamp;
use kairos_server::plugin::cache::CodeCache;
use kairos_server::plugin::conformance::{UpdateShape, horizon_case, pending_case};
use kairos_server::plugin::{
    InstanceMode, PluginOptions, PluginSource, WasmHorizonPolicy, WasmPriorityPolicy,
};
use rand::SeedableRng;
use rand::rngs::StdRng;

fn plugin(name: &str) -> PluginSource {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../plugins/build")
        .join(format!("{name}.wasm"));
    assert!(
        path.exists(),
        "{} is missing: run `bash plugins/build.sh` first",
        path.display()
    );
    PluginSource::File(path)
}

fn options(base: PluginOptions, mode: InstanceMode) -> PluginOptions {
    let cache = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../plugins/build/cache");
    PluginOptions {
        deadline: Duration::from_secs(1),
        memory_limit: 256 << 20,
        reload_poll: None,
        instance_mode: mode,
        cache: CodeCache::open(cache).ok(),
        ..base
    }
}

/// A fallback that panics: a bench must measure the plugin, never the fallback.
struct Never;

impl HorizonPolicy for Never {
    fn name(&self) -> &str {
        "never"
    }
    fn choose(&mut self, _: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        panic!("plugin failed during the bench")
    }
}

impl PriorityPolicy for Never {
    fn name(&self) -> &str {
        "never"
    }
    fn order(
        &mut self,
        _: Timestamp,
        _: &[PendingView],
        _: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        panic!("plugin failed during the bench")
    }
}

fn horizon(c: &mut Criterion) {
    let mut group = c.benchmark_group("horizon 50x10x7");
    let mut rng = StdRng::seed_from_u64(1);
    let realistic = horizon_case(
        &mut rng,
        "realistic",
        "",
        (1, 10, 50, 7),
        UpdateShape::Realistic,
    );
    let converged = horizon_case(
        &mut rng,
        "converged",
        "",
        (1, 10, 50, 7),
        UpdateShape::AllConverged,
    );
    let no_params = PolicyParams::new();
    let h8: PolicyParams = [("h".to_string(), 8.0)].into();

    let cases: [(&str, &str, &_, &PolicyParams); 3] = [
        ("threshold", "realistic chunk", &realistic, &no_params),
        (
            "threshold",
            "converged chunk (full scan)",
            &converged,
            &no_params,
        ),
        ("static", "h=8", &realistic, &h8),
    ];
    for (name, input_name, case, params) in cases {
        let mut case = (*case).clone();
        case.bounds = (1, 50);
        let input = case.input(params);
        let mut native: Box<dyn HorizonPolicy> = match name {
            "threshold" => Box::new(Threshold::default()),
            _ => Box::new(StaticHorizon { h: 8 }),
        };
        let mut wasm = WasmHorizonPolicy::load(
            &plugin(name),
            options(PluginOptions::horizon(), InstanceMode::Reuse),
            Box::new(Never),
        )
        .unwrap();
        assert_eq!(native.choose(&input), wasm.choose(&input), "twins disagree");
        group.bench_function(
            BenchmarkId::new(format!("{name} native"), input_name),
            |b| b.iter(|| native.choose(black_box(&input))),
        );
        group.bench_function(
            BenchmarkId::new(format!("{name} wasm (C)"), input_name),
            |b| b.iter(|| wasm.choose(black_box(&input))),
        );
    }
    let mut case = realistic.clone();
    case.bounds = (1, 50);
    let input = case.input(&no_params);
    let mut fresh = WasmHorizonPolicy::load(
        &plugin("threshold"),
        options(PluginOptions::horizon(), InstanceMode::Fresh),
        Box::new(Never),
    )
    .unwrap();
    group.bench_function(
        BenchmarkId::new(
            "threshold wasm (C), fresh instance per call",
            "realistic chunk",
        ),
        |b| b.iter(|| fresh.choose(black_box(&input))),
    );
    group.finish();
}

fn priority(c: &mut Criterion) {
    let mut group = c.benchmark_group("priority");
    let mut rng = StdRng::seed_from_u64(2);
    let lists: Vec<(usize, Timestamp, Vec<PendingView>)> = [10usize, 100, 1_000]
        .into_iter()
        .map(|n| {
            let (now, pending) = pending_case(&mut rng, n);
            (n, now, pending)
        })
        .collect();
    for (name, file) in [
        ("fifo", "fifo"),
        ("plas", "plas"),
        ("kairos", "kairos"),
        ("srw", "srw"),
        ("kairos", "kairos_py"),
        ("fifo", "fifo_v0_1"),
    ] {
        let mut native = build_policy(&name.parse::<PolicySpec>().unwrap()).unwrap();
        let mut wasm = WasmPriorityPolicy::load(
            &plugin(file),
            &PolicyParams::new(),
            options(PluginOptions::priority(), InstanceMode::Reuse),
            Box::new(Never),
        )
        .unwrap();
        if name == "srw" {
            // A trained SRW, as in service: hint-less due requests read the learned index.
            for i in 0..200u32 {
                let summary = FinishedTask {
                    task: TaskId(u64::from(i)),
                    rounds: 5 + i % 60,
                    latency: Duration::from_secs(30),
                    attained_service: Duration::from_secs(2),
                    wait: Duration::from_secs(4),
                };
                native.task_finished(&summary);
                wasm.call_task_finished(&summary).unwrap();
            }
        }
        let language = match file {
            f if f.ends_with("_py") => "Python",
            f if f.ends_with("_v0_1") => "C, WIT 0.1.0",
            _ => "C",
        };
        for (n, now, pending) in &lists {
            let mut order = Vec::with_capacity(*n);
            let mut want = Vec::new();
            native.order(*now, pending, &mut want).unwrap();
            wasm.order(*now, pending, &mut order).unwrap();
            assert_eq!(order, want, "twins disagree");
            if language == "C" {
                group.bench_function(BenchmarkId::new(format!("{name} native"), n), |b| {
                    b.iter(|| {
                        order.clear();
                        native.order(*now, black_box(pending), &mut order)
                    })
                });
            }
            group.bench_function(
                BenchmarkId::new(format!("{name} wasm ({language})"), n),
                |b| {
                    b.iter(|| {
                        order.clear();
                        wasm.order(*now, black_box(pending), &mut order)
                    })
                },
            );
        }
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .without_plots()
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2))
        .sample_size(30);
    targets = horizon, priority
}
criterion_main!(benches);
