//! The fleet page in a real browser, against a live fleet (issue #32): headless Chromium loads
//! `/` from the metrics listener of a `kairos serve` with two workers, two plugins and six
//! robots. The test keeps every `/api/fleet` body the page itself fetched (the DevTools
//! protocol's network events), and once the page has rendered a few of them reads its DOM: the
//! robots, tasks, queue and latency values shown must be those of the snapshot it rendered, and
//! the engines and plugins tables must list the snapshot's. A screenshot of the page goes to
//! `target/artifacts/fleet-page.png` (`docs/fleet-page.png` is one).

use std::time::Instant;

use serde_json::{Value, json};

use crate::browser::Browser;
use crate::live_fleet::{GIVE_UP, LiveFleet, http_get};
use crate::repo_root;

/// What the test reads off the page, in one evaluation (so from one rendered snapshot).
const READ_PAGE: &str = r#"(() => {
  const value = (id) => document.getElementById(id).dataset.value;
  const text = (id) => document.getElementById(id).textContent;
  const rows = (id) => Array.from(document.querySelectorAll('#' + id + ' tbody tr'));
  return {
    state: document.body.dataset.state,
    snapshots: Number(document.body.dataset.snapshots || 0),
    robots: text('robots-connected'),
    tasks: text('tasks-open'),
    queue: text('queue-depth'),
    running: text('queue-running'),
    answered: text('rounds-answered'),
    latency: ['p50', 'p90', 'p99'].map((q) => [value('latency-' + q), text('latency-' + q)]),
    engines: rows('engines').map((r) => r.dataset.engine),
    plugins: rows('plugins').map((r) => r.dataset.policy),
    latencyPoints: Number(document.getElementById('latency-chart').dataset.points || 0),
    horizonRounds: Number(document.getElementById('horizon-chart').dataset.rounds || 0),
    html: document.documentElement.outerHTML,
  };
})()"#;

/// Robots in the fleet.
const ROBOTS: u64 = 6;

/// Snapshots the page must have rendered before it is read (its charts then have history).
const RENDERED: u64 = 5;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs Debian's chromium and the built plugins; scripts/test.sh installs both and runs it"]
async fn the_fleet_page_renders_what_the_server_reports() {
    crate::browser::chromium_binary();
    let fleet = tokio::task::spawn_blocking(|| LiveFleet::start(ROBOTS))
        .await
        .unwrap();
    let (status, _) = http_get(fleet.metrics, "/");
    assert_eq!(status, 200);

    let mut browser = Browser::launch().await;
    let page = browser.page(1280, 860).await;
    browser
        .call(
            Some(&page),
            "Page.navigate",
            json!({ "url": format!("http://{}/", fleet.metrics) }),
        )
        .await;

    // The snapshots the page fetched, in order: the request ids of `/api/fleet`, and each body
    // once it has arrived.
    let mut requests: Vec<String> = Vec::new();
    let mut bodies: Vec<Value> = Vec::new();
    let started = Instant::now();
    let read = loop {
        assert!(
            started.elapsed() < GIVE_UP,
            "the page did not render {RENDERED} snapshots"
        );
        let event = browser.event().await;
        match event["method"].as_str() {
            Some("Network.responseReceived")
                if event["params"]["response"]["url"]
                    .as_str()
                    .is_some_and(|u| u.ends_with("/api/fleet")) =>
            {
                assert_eq!(event["params"]["response"]["status"], 200);
                requests.push(event["params"]["requestId"].as_str().unwrap().into());
            }
            Some("Network.loadingFinished") => {
                let id = event["params"]["requestId"].as_str().unwrap_or_default();
                if requests.iter().any(|r| r == id) {
                    let body = browser
                        .call(
                            Some(&page),
                            "Network.getResponseBody",
                            json!({ "requestId": id }),
                        )
                        .await;
                    bodies.push(serde_json::from_str(body["body"].as_str().unwrap()).unwrap());
                }
            }
            _ => {}
        }
        if bodies.len() as u64 >= RENDERED {
            let read = browser.evaluate(&page, READ_PAGE).await;
            let rendered = read["snapshots"].as_u64().unwrap();
            // The page fetches one snapshot at a time: the n-th rendered is the n-th fetched.
            if rendered >= RENDERED && rendered as usize <= bodies.len() {
                break read;
            }
        }
    };
    let shown = &bodies[read["snapshots"].as_u64().unwrap() as usize - 1];

    assert_eq!(read["state"], "live");
    assert_eq!(shown["robots"]["connected"], ROBOTS, "{shown}");
    for (key, field) in [
        ("robots", &shown["robots"]["connected"]),
        ("tasks", &shown["tasks"]["open"]),
        ("queue", &shown["queue"]["depth"]),
        ("running", &shown["queue"]["running"]),
        ("answered", &shown["rounds"]["answered"]),
    ] {
        assert_eq!(read[key].as_str().unwrap(), field.to_string(), "{key}");
    }
    let latency = &shown["window"]["latency_seconds"];
    for (i, q) in ["p50", "p90", "p99"].iter().enumerate() {
        let seconds = latency[q]
            .as_f64()
            .unwrap_or_else(|| panic!("no {q} in {shown}"));
        let [value, text] = [&read["latency"][i][0], &read["latency"][i][1]];
        assert_eq!(
            value.as_str().unwrap().parse::<f64>().unwrap(),
            seconds,
            "{q}: the value the page holds is the server's"
        );
        // Shown in milliseconds with one decimal.
        let shown_ms: f64 = text
            .as_str()
            .unwrap()
            .strip_suffix(" ms")
            .unwrap()
            .parse()
            .unwrap();
        assert!(
            (shown_ms - seconds * 1e3).abs() <= 0.05 + 1e-9,
            "{q}: {text} vs {seconds} s"
        );
    }
    let names = |list: &Value, key: &str| -> Vec<String> {
        let mut names: Vec<String> = list
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v[key].as_str().unwrap().to_string())
            .collect();
        names.sort();
        names
    };
    let mut engines: Vec<String> = read["engines"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    engines.sort();
    assert_eq!(engines, names(&shown["engines"], "name"));
    assert_eq!(engines.len(), 2, "the two workers: {engines:?}");
    let mut plugins: Vec<String> = read["plugins"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    plugins.sort();
    assert_eq!(plugins, names(&shown["plugins"], "policy"));
    assert_eq!(plugins, ["kairos", "threshold"]);
    let horizon_rounds: u64 = shown["window"]["horizon"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| b["count"].as_u64().unwrap())
        .sum();
    assert_eq!(read["horizonRounds"], horizon_rounds);
    assert!(horizon_rounds > 0, "the horizon chart has rounds");
    assert!(
        read["latencyPoints"].as_u64().unwrap() > 0,
        "the latency chart has points"
    );

    // No robot token reaches the page.
    let html = read["html"].as_str().unwrap();
    let tokens = robot_tokens(&fleet.dir.path().join("data"));
    assert!(!tokens.is_empty(), "the data directory has robot tokens");
    for token in &tokens {
        assert!(
            !html.contains(token.as_str()),
            "a robot token is on the page"
        );
    }

    let png = browser.screenshot(&page).await;
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"), "a PNG");
    let artifacts = repo_root().join("target/artifacts");
    std::fs::create_dir_all(&artifacts).unwrap();
    std::fs::write(artifacts.join("fleet-page.png"), &png).unwrap();
}

/// The robot tokens in a server's data directory (every quoted string of 20 characters or more in
/// its token files).
fn robot_tokens(data: &std::path::Path) -> Vec<String> {
    let mut tokens = Vec::new();
    for entry in std::fs::read_dir(data).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        if !name.contains("token") || !path.is_file() {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        for word in text.split(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '_')) {
            if word.len() >= 20 {
                tokens.push(word.to_string());
            }
        }
    }
    tokens
}
