//! `kairos demo`'s code path, small: the built-in flow head profiled at start, a fresh server per
//! scheduler, two robots over QUIC, a few rounds each, and the summary and plot at the end.

use kairos_bench::demo::{DemoOptions, Horizons, execute, fleet};

#[test]
fn a_small_demo_answers_every_round_of_every_scheduler_and_writes_its_summary() {
    let dir = tempfile::tempdir().unwrap();
    let args = DemoOptions {
        robots: 2,
        task_s: 0.5,
        stagger_s: 0.05,
        profile_max_batch: 1,
        out: dir.path().join("demo"),
        ..DemoOptions::default()
    };
    let planned = fleet(&args);
    let report = execute(&args, std::sync::Arc::new(())).unwrap();

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
    assert!(summary.contains("Lowest average latency"), "{summary}");
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
