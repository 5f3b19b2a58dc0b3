//! `kairos demo`'s code path, small: the built-in flow head profiled at start, a fresh server per
//! scheduler, two robots over QUIC, a few rounds each, and the summary and plot at the end; and
//! the fleet the demo sizes from the profile it measures.

use kairos_bench::demo::workload::sizing_cycle;
use kairos_bench::demo::{DEFAULT_LOAD, DemoOptions, Horizons, execute, fleet, size_fleet};
use kairos_server::config::EngineConfig;
use kairos_server::pool::{BuildEvent, ModelSchemes, build_pool};

/// The demo's fleet, sized from the profile this machine measures for the built-in flow head,
/// contends the engine: the work its tasks bring over its arrival span is about 90% of what the
/// engine serves at its saturation batch, and more robots run at once than one batch holds. This
/// checks the sizing rule on a real profile, not how a run turns out.
#[test]
fn the_auto_sized_fleet_contends_the_measured_engine() {
    let mut measured = None;
    let config = EngineConfig {
        profile_max_batch: 4,
        ..EngineConfig::default()
    };
    let _pool = build_pool(&[config], &ModelSchemes::new(), |event| {
        if let BuildEvent::Ready { profile, .. } = event {
            measured = Some(profile);
        }
    })
    .unwrap();
    let profile = measured.unwrap();
    for args in [
        DemoOptions::default(),
        DemoOptions::default().resolve_quick(Some(std::ffi::OsStr::new("1"))),
    ] {
        let sizing = size_fleet(&profile, &args);
        assert!(sizing.auto_robots && sizing.auto_stagger);
        let tasks = fleet(&args, &sizing);
        assert_eq!(tasks.len(), sizing.robots as usize);
        assert!(tasks.len() >= 2, "{sizing:?}");

        // Independently of the rule's own arithmetic: the engine time the fleet's rounds take at
        // the saturation batch, over the time the robots keep arriving.
        let batch = profile.max_batch;
        let per_request_s = profile.latency(batch).as_secs_f64() / f64::from(batch);
        let cycle = sizing_cycle(
            args.static_h,
            0.5,
            args.control_hz,
            profile.latency(batch).as_secs_f64(),
        );
        let work_s: f64 = tasks
            .iter()
            .map(|t| t.actions as f64 / cycle.actions * per_request_s)
            .sum();
        let span_s = tasks.last().unwrap().start.as_secs_f64();
        // `n` arrivals span `n − 1` gaps.
        let offered = work_s * (tasks.len() - 1) as f64 / tasks.len() as f64 / span_s;
        assert!(
            (0.85..=0.95).contains(&offered),
            "offered load {offered:.2} ({sizing:?}, profile {profile:?})"
        );
        assert!((sizing.load - DEFAULT_LOAD).abs() < 1e-9, "{sizing:?}");
        assert!(
            sizing.concurrent > f64::from(batch),
            "more robots at once than a batch holds: {sizing:?}"
        );
        // A static H asks at least once per H actions.
        assert!(cycle.actions <= f64::from(args.static_h));
    }
}

#[test]
fn a_small_demo_answers_every_round_of_every_scheduler_and_writes_its_summary() {
    let dir = tempfile::tempdir().unwrap();
    let args = DemoOptions {
        robots: Some(2),
        task_s: 0.5,
        stagger_s: Some(0.05),
        profile_max_batch: 1,
        out: dir.path().join("demo"),
        ..DemoOptions::default()
    };
    let report = execute(&args, std::sync::Arc::new(())).unwrap();
    assert_eq!(
        (report.sizing.robots, report.sizing.stagger_s),
        (2, 0.05),
        "--robots and --stagger-s override the sizing"
    );
    let planned = fleet(&args, &report.sizing);

    assert!(report.engine.contains("flow-head"), "{}", report.engine);
    let labels: Vec<&str> = report
        .results
        .iter()
        .map(|r| r.run.label.as_str())
        .collect();
    assert_eq!(
        labels,
        [
            "FIFO, H=10",
            "Autellix, H=10",
            "Kairos, dyn. H",
            "SRW (ours), dyn. H"
        ]
    );
    for r in &report.results {
        assert!(r.failures.is_empty(), "{}: {:?}", r.run.label, r.failures);
        assert_eq!(
            r.tasks.len(),
            planned.len(),
            "{}: every robot finished",
            r.run.label
        );
        // Every round a robot sent was generated once and answered, none failed.
        assert_eq!(
            r.server.driver.replies as usize,
            r.round_count(),
            "{}",
            r.run.label
        );
        assert_eq!(r.server.driver.failed, 0, "{}", r.run.label);
        assert_eq!(r.server.driver.tasks_ended as usize, planned.len());
        for (task, plan) in r.tasks.iter().zip(&planned) {
            assert_eq!(task.failed_rounds, 0);
            assert!(
                task.actions_executed >= plan.actions,
                "{}: {} of {} actions",
                r.run.label,
                task.actions_executed,
                plan.actions
            );
            assert!(task.latency_us() as f64 >= plan.actions as f64 / args.control_hz * 1e6 * 0.9);
        }
        if !r.run.dynamic() {
            assert!(
                r.tasks
                    .iter()
                    .flat_map(|t| &t.rounds)
                    .all(|round| round.horizon == args.static_h && round.policy == "static"),
                "{}: the baselines execute the static H",
                r.run.label
            );
        } else {
            assert!(
                r.tasks
                    .iter()
                    .flat_map(|t| &t.rounds)
                    .all(|round| round.policy == "threshold" && round.horizon >= args.h_min),
                "{}: the dynamic horizon comes from the threshold policy",
                r.run.label
            );
        }
    }

    let summary = std::fs::read_to_string(args.out.join("summary.md")).unwrap();
    assert_eq!(summary, report.summary);
    for label in labels {
        assert!(summary.contains(label), "{label} missing from\n{summary}");
    }
    assert!(
        summary.starts_with("# kairos demo\n\n**Kairos, dyn. H: average task latency")
            || summary.starts_with("# kairos demo\n\n**Kairos, dyn. H and FIFO, H=10"),
        "the summary leads with Kairos against FIFO:\n{summary}"
    );
    let table = summary.find("| Scheduler |").unwrap();
    assert!(summary.find("engine busy").unwrap() < table);
    let plot = report.plot.unwrap();
    let png = std::fs::read(&plot).unwrap();
    assert_eq!(
        &png[..8],
        b"\x89PNG\r\n\x1a\n",
        "{} is a PNG",
        plot.display()
    );
}

#[test]
fn dynamic_horizons_for_every_scheduler_when_asked() {
    let args = DemoOptions {
        horizons: Horizons::Dynamic,
        schedulers: vec!["fifo".into(), "kairos:buckets=5".into()],
        ..DemoOptions::default()
    };
    let runs = kairos_bench::demo::scheduler_runs(&args).unwrap();
    assert!(runs.iter().all(|r| r.dynamic()));
    assert_eq!(runs[1].policy.to_string(), "kairos:buckets=5");
    let bad = DemoOptions {
        schedulers: vec!["lottery".into()],
        ..DemoOptions::default()
    };
    let error = kairos_bench::demo::scheduler_runs(&bad).unwrap_err();
    assert!(error.to_string().contains("lottery"), "{error}");
}
