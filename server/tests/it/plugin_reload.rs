//! Hot reload: a changed plugin file is compiled in the background and swapped in between two
//! decisions; no decision in flight is dropped or answered by the fallback, a broken new
//! version is ignored, and a reload lifts a quarantine.

use std::path::Path;
use std::sync::{Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

use crate::plugin_common::*;
use kairos_core::horizon::{ChunkView, HorizonError, HorizonInput, HorizonPolicy, PolicyParams};
use kairos_server::plugin::{PluginOptions, PluginSource, WasmHorizonPolicy};

/// Answers 1, so a fallback answer is visible (the fixtures answer h_min = 2 or h_max = 40).
struct One;

impl HorizonPolicy for One {
    fn name(&self) -> &str {
        "one"
    }
    fn choose(&mut self, _: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        Ok(1)
    }
}

/// The watcher's refusals of new versions, per plugin name: the error it logs when a changed
/// file does not load ("keeping the running version") is the one sign of a refusal an operator
/// gets, and the event this test waits for (no sleep that a loaded machine could outlast).
#[derive(Default)]
struct Refusals {
    by_plugin: Mutex<Vec<String>>,
    changed: Condvar,
}

impl Refusals {
    /// The process-wide log collector (installed once; the other tests of this binary log
    /// nothing at ERROR from the reload watcher's module with our plugin names).
    fn get() -> &'static Refusals {
        static REFUSALS: OnceLock<&'static Refusals> = OnceLock::new();
        REFUSALS.get_or_init(|| {
            use tracing_subscriber::layer::SubscriberExt;
            let refusals: &'static Refusals = Box::leak(Box::default());
            let subscriber = tracing_subscriber::registry().with(RefusalLayer(refusals));
            tracing::subscriber::set_global_default(subscriber)
                .expect("no other global subscriber in this test binary");
            refusals
        })
    }

    fn count(&self, plugin: &str) -> usize {
        let seen = self.by_plugin.lock().expect("not poisoned");
        seen.iter().filter(|p| *p == plugin).count()
    }

    /// Waits until the watcher of `plugin` has refused `n` versions. The limit only turns a
    /// watcher that never refuses into a failure instead of a hang.
    fn wait_for(&self, plugin: &str, n: usize) {
        let limit = Duration::from_secs(60);
        let seen = self.by_plugin.lock().expect("not poisoned");
        let (seen, wait) = self
            .changed
            .wait_timeout_while(seen, limit, |seen| {
                seen.iter().filter(|p| *p == plugin).count() < n
            })
            .expect("not poisoned");
        assert!(
            !wait.timed_out(),
            "{plugin}: {} refusals, expected {n}",
            seen.len()
        );
    }
}

struct RefusalLayer(&'static Refusals);

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for RefusalLayer {
    /// Only the watcher's errors: the other tests of the binary pay nothing for the collector.
    fn enabled(
        &self,
        meta: &tracing::Metadata<'_>,
        _: tracing_subscriber::layer::Context<'_, S>,
    ) -> bool {
        *meta.level() == tracing::Level::ERROR && meta.target().ends_with("plugin::reload")
    }

    fn on_event(&self, event: &tracing::Event<'_>, _: tracing_subscriber::layer::Context<'_, S>) {
        let meta = event.metadata();
        if *meta.level() != tracing::Level::ERROR || !meta.target().ends_with("plugin::reload") {
            return;
        }
        struct Plugin(Option<String>);
        impl tracing::field::Visit for Plugin {
            fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
                if field.name() == "plugin" {
                    self.0 = Some(format!("{value:?}"));
                }
            }
        }
        let mut plugin = Plugin(None);
        event.record(&mut plugin);
        if let Some(name) = plugin.0 {
            self.0.by_plugin.lock().expect("not poisoned").push(name);
            self.0.changed.notify_all();
        }
    }
}

/// Replaces `path` atomically, the way a deployment should (write aside, rename).
fn install(path: &Path, wasm: &[u8]) {
    let tmp = path.with_extension("new");
    std::fs::write(&tmp, wasm).expect("write the new version aside");
    std::fs::rename(&tmp, path).expect("rename it over the plugin");
}

struct Robot {
    updates: Vec<f32>,
    actions: Vec<f32>,
    params: PolicyParams,
}

impl Robot {
    fn new() -> Self {
        Robot {
            updates: vec![0.1; 10 * 50 * 7],
            actions: vec![0.0; 50 * 7],
            params: PolicyParams::new(),
        }
    }

    fn decide(&self, policy: &mut WasmHorizonPolicy) -> usize {
        let input = HorizonInput {
            chunk: ChunkView {
                samples: 1,
                steps: 10,
                chunk_len: 50,
                action_dim: 7,
                updates: &self.updates,
                actions: &self.actions,
            },
            h_min: 1,
            h_max: 40,
            control_hz: 30.0,
            round_index: 0,
            recent_horizons: &[],
            params: &self.params,
            load: None,
        };
        policy.choose(&input).expect("always answered")
    }
}

/// Decides until the answer becomes `want` (or `limit` passes); every answer on the way must
/// be `before` or `want`: never the fallback's.
fn decide_until(
    policy: &mut WasmHorizonPolicy,
    robot: &Robot,
    before: usize,
    want: usize,
    limit: Duration,
) -> usize {
    let started = Instant::now();
    let mut decisions = 0;
    loop {
        let h = robot.decide(policy);
        decisions += 1;
        assert!(
            h == before || h == want,
            "decision {decisions} answered {h}"
        );
        if h == want {
            return decisions;
        }
        assert!(
            started.elapsed() < limit,
            "no reload after {decisions} decisions"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
}

fn options() -> PluginOptions {
    PluginOptions {
        reload_poll: Some(Duration::from_millis(10)),
        deadline: Duration::from_millis(100),
        ..PluginOptions::horizon()
    }
}

#[test]
fn a_new_version_is_swapped_in_between_decisions_and_broken_ones_are_ignored() {
    let refusals = Refusals::get();
    let dir = tempfile::tempdir().unwrap();
    // The file stem names the plugin in the watcher's log.
    let path = dir.path().join("swapped.wasm");
    install(&path, &horizon_component("(i32.const 2)"));
    let mut policy =
        WasmHorizonPolicy::load(&PluginSource::File(path.clone()), options(), Box::new(One))
            .unwrap();
    let robot = Robot::new();
    assert_eq!(robot.decide(&mut policy), 2);

    install(&path, &horizon_component(HORIZON_H_MAX));
    decide_until(&mut policy, &robot, 2, 40, Duration::from_secs(10));
    let stats = policy.stats();
    assert_eq!(stats.reloads, 1);
    assert_eq!(
        stats.fallbacks, 0,
        "no decision fell back during the swap: {stats:?}"
    );

    // Garbage, then a plugin for the other world: each is read and refused by the watcher (we
    // wait for its refusal before installing the next, so neither is skipped unread), and the
    // running version answers throughout.
    assert_eq!(refusals.count("swapped"), 0);
    install(&path, b"\0asm garbage");
    refusals.wait_for("swapped", 1);
    assert_eq!(robot.decide(&mut policy), 40);
    install(&path, &priority_component(PRIORITY_IDENTITY));
    refusals.wait_for("swapped", 2);
    for _ in 0..10 {
        assert_eq!(robot.decide(&mut policy), 40);
    }
    let stats = policy.stats();
    assert_eq!((stats.reloads, stats.fallbacks), (1, 0), "{stats:?}");
}

#[test]
fn reloading_a_fixed_version_lifts_the_quarantine() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("policy.wasm");
    install(&path, &horizon_component(HORIZON_TRAP));
    let mut policy = WasmHorizonPolicy::load(
        &PluginSource::File(path.clone()),
        PluginOptions {
            quarantine_after: 2,
            probation: 1_000_000,
            ..options()
        },
        Box::new(One),
    )
    .unwrap();
    let robot = Robot::new();
    for _ in 0..5 {
        assert_eq!(robot.decide(&mut policy), 1, "the fallback answers");
    }
    assert!(policy.stats().quarantined);

    install(&path, &horizon_component(HORIZON_H_MAX));
    decide_until(&mut policy, &robot, 1, 40, Duration::from_secs(10));
    let stats = policy.stats();
    assert!(!stats.quarantined, "{stats:?}");
    assert_eq!(stats.reloads, 1);
}
