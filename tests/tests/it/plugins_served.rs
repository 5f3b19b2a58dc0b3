//! Policy plugins in the live server: `[[plugin]]` entries load the shipped C components, robots
//! select the horizon plugin by name over QUIC, and the scheduler orders requests with the
//! priority plugin. The plugins' answers reach the robots: the same fleet against a server with
//! the native twins gets the same horizons round for round. Run `plugins/build.sh` first (CI
//! does); a missing plugin fails the test.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeMap;

use kairos_sdk::protocol::HorizonSelection;
use kairos_server::config::{Config, PluginConfig};
use kairos_tests::harness::{RobotPlan, ServerOptions, TaskLog, TestServer, run_fleet};

const ROBOTS: u64 = 8;
const ROUNDS: u64 = 5;

fn plugin(name: &str, file: &str) -> PluginConfig {
    let path = kairos_tests::plugins::shipped_plugin(file.trim_end_matches(".wasm"));
    PluginConfig {
        name: Some(name.into()),
        // A generous deadline: a loaded CI machine must not turn a slow call into a fallback.
        deadline_ms: Some(2_000),
        ..PluginConfig::file(path)
    }
}

fn threshold_params(config: &mut Config) {
    // Not the native defaults, so that a fallback answer (native defaults) would differ.
    config.horizon.params = BTreeMap::from([("t".into(), 0.25), ("h_min".into(), 3.0)]);
}

fn with_plugins(config: &mut Config) {
    config.plugins = vec![
        plugin("wasm-threshold", "threshold.wasm"),
        plugin("wasm-static", "static.wasm"),
        plugin("wasm-kairos", "kairos.wasm"),
    ];
    config.horizon.policy = "wasm-threshold".into();
    threshold_params(config);
    config.scheduler.policy = "wasm-kairos".parse().unwrap();
}

fn with_natives(config: &mut Config) {
    config.horizon.policy = "threshold".into();
    threshold_params(config);
    config.scheduler.policy = "kairos".parse().unwrap();
}

/// Half the fleet asks for the static plugin (`h = 5`; the fallback would give the threshold
/// policy's answer), half takes the server's default horizon policy.
async fn fleet(tweak: fn(&mut Config), static_name: &str) -> Vec<TaskLog> {
    let server = TestServer::start(ServerOptions {
        max_batch: 4,
        tweak,
        ..ServerOptions::default()
    })
    .await
    .unwrap();
    let plans = (0..ROBOTS)
        .map(|i| RobotPlan {
            task: 100 + i,
            rounds: ROUNDS,
            control_hz: 200.0,
            send_ahead: 3,
            horizon: (i % 2 == 0).then(|| HorizonSelection {
                policy: static_name.into(),
                params: BTreeMap::from([("h".to_string(), 5.0)]),
                samples: 1,
            }),
            state1: 0.1 * (i % 4) as f32,
        })
        .collect();
    let logs = run_fleet(&server, plans).await.unwrap();
    let report = server.shutdown().await;
    assert_eq!(
        report.driver.replies,
        ROBOTS * ROUNDS,
        "every round answered"
    );
    assert_eq!(report.driver.failed, 0);
    logs
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn configured_plugins_answer_robots_like_their_native_twins() {
    let plugged = fleet(with_plugins, "wasm-static").await;
    let native = fleet(with_natives, "static").await;
    let horizons = |logs: &[TaskLog]| -> Vec<Vec<u32>> {
        logs.iter()
            .map(|l| l.rounds.iter().map(|r| r.horizon).collect())
            .collect()
    };
    for log in &plugged {
        assert_eq!(log.rounds.len() as u64, ROUNDS);
        for round in &log.rounds {
            let expected = if log.task % 2 == 0 {
                "wasm-static"
            } else {
                "wasm-threshold"
            };
            assert_eq!(round.policy, expected, "task {}", log.task);
            if log.task % 2 == 0 {
                assert_eq!(round.horizon, 5);
            }
        }
    }
    assert_eq!(horizons(&plugged), horizons(&native));
    // The threshold cut moves with state[1]: the comparison is not between constants.
    let distinct: std::collections::BTreeSet<u32> = plugged
        .iter()
        .filter(|l| l.task % 2 == 1)
        .flat_map(|l| l.rounds.iter().map(|r| r.horizon))
        .collect();
    assert!(distinct.len() > 1, "threshold horizons {distinct:?}");
}

#[tokio::test]
async fn a_plugin_of_the_wrong_world_or_a_missing_file_stops_the_start_with_its_name() {
    let wrong = TestServer::start(ServerOptions {
        tweak: |c| {
            // A priority plugin where a horizon policy is expected as the default.
            c.plugins = vec![plugin("wasm-kairos", "kairos.wasm")];
            c.horizon.policy = "wasm-kairos".into();
        },
        ..ServerOptions::default()
    })
    .await;
    let error = format!("{:#}", wrong.err().unwrap());
    assert!(error.contains("wasm-kairos"), "{error}");

    let missing = TestServer::start(ServerOptions {
        tweak: |c| c.plugins = vec![PluginConfig::file("/nonexistent/p.wasm")],
        ..ServerOptions::default()
    })
    .await;
    let error = format!("{:#}", missing.err().unwrap());
    assert!(error.contains("/nonexistent/p.wasm"), "{error}");
}
