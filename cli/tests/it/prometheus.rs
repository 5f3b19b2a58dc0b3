//! The shipped monitoring config against a real Prometheus (issue #32): Debian's `prometheus`
//! scrapes a live fleet (`kairos serve` with two workers, two plugins and robots) every second
//! and evaluates `deploy/monitoring/kairos.rules.yml`. Then every PromQL expression of the
//! dashboard (`deploy/monitoring/kairos-fleet.dashboard.json`) and of the alert rules is run
//! through its query API, and each must return data:
//!
//! - a dashboard expression as Grafana sends it (`$__rate_interval` as 1m, `$__range` as 5m,
//!   `$job` as every job);
//! - an alert expression with each comparison made a `bool` one (`a > bool b`): it then answers
//!   0 or 1 for every series instead of filtering them out, so an empty answer means a metric or
//!   a label the rule reads does not exist, never that the fleet is healthy.
//!
//! Every metric name an expression reads must also be one Prometheus scraped. Prometheus must
//! report every rule healthy, and one alert must really fire: a worker is killed, and
//! `KairosWorkerRemoved` (no `for`) must become active.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::live_fleet::{GIVE_UP, LiveFleet};
use crate::repo_root;

/// Debian's Prometheus binaries, or a test failure that says how to get them.
fn prometheus_binary(name: &str) -> PathBuf {
    let path = PathBuf::from("/usr/bin").join(name);
    assert!(
        path.exists(),
        "{} not found: install Debian's Prometheus (`apt-get install prometheus`, which brings \
         prometheus and promtool; scripts/test.sh does)",
        path.display()
    );
    path
}

/// A Prometheus server killed when dropped.
struct Prometheus {
    child: Child,
    addr: SocketAddr,
}

impl Drop for Prometheus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn percent_encode(text: &str) -> String {
    let mut out = String::new();
    for b in text.bytes() {
        if b.is_ascii_alphanumeric() || b"-_.~".contains(&b) {
            out.push(char::from(b));
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// `GET path` over HTTP/1.0 (so the body is not chunked): status and body; `None` if nothing
/// listens yet.
fn get(addr: SocketAddr, path: &str) -> Option<(u16, String)> {
    let mut stream = TcpStream::connect(addr).ok()?;
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    write!(stream, "GET {path} HTTP/1.0\r\nHost: prometheus\r\n\r\n").ok()?;
    let mut response = String::new();
    stream.read_to_string(&mut response).ok()?;
    let (head, body) = response.split_once("\r\n\r\n")?;
    let status = head.get(9..12)?.parse().ok()?;
    Some((status, body.to_string()))
}

/// `GET path`, answered 200, parsed as JSON.
fn get_json(addr: SocketAddr, path: &str) -> Value {
    let (status, body) = get(addr, path).unwrap_or_else(|| panic!("no answer to {path}"));
    assert_eq!(status, 200, "{path}: {body}");
    serde_json::from_str(&body).unwrap_or_else(|e| panic!("{e}: {body}"))
}

impl Prometheus {
    /// Starts Prometheus scraping `target` every second with `rules` loaded; returns once it is
    /// ready.
    fn start(dir: &Path, target: SocketAddr, rules: &Path) -> Prometheus {
        // A free port for its web listener (Prometheus cannot report one it picked itself).
        let addr = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap();
        let config = dir.join("prometheus.yml");
        std::fs::write(
            &config,
            format!(
                "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\n  evaluation_interval: 1s\n\
                 rule_files:\n  - {}\n\
                 scrape_configs:\n  - job_name: kairos-scheduler\n    static_configs:\n      - targets: ['{target}']\n",
                rules.display()
            ),
        )
        .unwrap();
        let child = Command::new(prometheus_binary("prometheus"))
            .arg(format!("--config.file={}", config.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.join("tsdb").display()
            ))
            .arg(format!("--web.listen-address={addr}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let prometheus = Prometheus { child, addr };
        // `/-/ready` answers 503 while the storage starts, 200 once queries are served.
        prometheus.wait_for("Prometheus ready", || {
            get(addr, "/-/ready").is_some_and(|(status, _)| status == 200)
        });
        prometheus
    }

    fn wait_for(&self, what: &str, done: impl Fn() -> bool) {
        let started = Instant::now();
        while !done() {
            assert!(started.elapsed() < GIVE_UP, "gave up waiting for {what}");
            std::thread::sleep(Duration::from_millis(250));
        }
    }

    /// An instant query's result vector (or scalar as a one-element list).
    fn query(&self, expr: &str) -> Vec<Value> {
        let answer = get_json(
            self.addr,
            &format!("/api/v1/query?query={}", percent_encode(expr)),
        );
        assert_eq!(answer["status"], "success", "`{expr}`: {answer}");
        match answer["data"]["resultType"].as_str() {
            Some("vector") | Some("matrix") => answer["data"]["result"].as_array().unwrap().clone(),
            _ => vec![answer["data"]["result"].clone()],
        }
    }
}

/// A rule of the rules file: its expression, and the labels its annotations show
/// (`{{ $labels.NAME }}`).
struct Rule {
    expr: String,
    shown_labels: Vec<String>,
}

/// Every rule in a rules file (its `expr` one line, as the file's header promises).
fn rules_of(text: &str) -> Vec<Rule> {
    let mut rules: Vec<Rule> = Vec::new();
    for line in text.lines().map(str::trim) {
        if line.starts_with("- alert:") {
            rules.push(Rule {
                expr: String::new(),
                shown_labels: Vec::new(),
            });
        } else if let (Some(rule), Some(expr)) = (rules.last_mut(), line.strip_prefix("expr: ")) {
            rule.expr = expr.to_string();
        } else if let Some(rule) = rules.last_mut() {
            let mut rest = line;
            while let Some(at) = rest.find("$labels.") {
                let name: String = rest[at + 8..]
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                    .collect();
                rest = &rest[at + 8 + name.len()..];
                rule.shown_labels.push(name);
            }
        }
    }
    assert!(
        rules.iter().all(|r| !r.expr.is_empty()),
        "one single-line expr per rule"
    );
    rules
}

/// Every `expr` of the dashboard's panels, and the metric its variables are read from.
fn dashboard_expressions(dashboard: &Value) -> (Vec<String>, Vec<String>) {
    let mut exprs = Vec::new();
    for panel in dashboard["panels"].as_array().unwrap() {
        for target in panel["targets"].as_array().unwrap() {
            exprs.push(target["expr"].as_str().unwrap().to_string());
        }
    }
    let mut variables = Vec::new();
    for variable in dashboard["templating"]["list"].as_array().unwrap() {
        if let Some(query) = variable["definition"].as_str() {
            variables.push(query.to_string());
        }
    }
    (exprs, variables)
}

/// An expression as Grafana sends it, its variables replaced.
fn as_grafana_sends(expr: &str) -> String {
    expr.replace("$__rate_interval", "1m")
        .replace("$__range", "5m")
        .replace("$job", ".+")
}

/// `expr` with every comparison made a `bool` comparison (outside label matchers and strings).
fn with_bool_comparisons(expr: &str) -> String {
    let chars: Vec<char> = expr.chars().collect();
    let mut out = String::new();
    let (mut braces, mut quoted) = (0usize, false);
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        let next = chars.get(i + 1).copied();
        if quoted {
            out.push(c);
            if c == '\\'
                && let Some(n) = next
            {
                out.push(n);
                i += 1;
            } else if c == '"' {
                quoted = false;
            }
            i += 1;
            continue;
        }
        match c {
            '"' => quoted = true,
            '{' => braces += 1,
            '}' => braces = braces.saturating_sub(1),
            _ => {}
        }
        let two: String = chars[i..chars.len().min(i + 2)].iter().collect();
        if braces == 0 && matches!(two.as_str(), "==" | "!=" | ">=" | "<=") {
            out.push_str(&two);
            out.push_str(" bool");
            i += 2;
            continue;
        }
        if braces == 0 && matches!(c, '>' | '<') {
            out.push(c);
            out.push_str(" bool");
            i += 1;
            continue;
        }
        out.push(c);
        i += 1;
    }
    out
}

/// The Kairos metric names `expr` reads (as written: `_bucket`, `_total`, ...).
fn metric_names(expr: &str) -> Vec<String> {
    let mut names = Vec::new();
    let mut rest = expr;
    while let Some(at) = rest.find("kairos_") {
        let name: String = rest[at..]
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        rest = &rest[at + name.len()..];
        names.push(name);
    }
    names
}

#[test]
fn comparisons_become_bool_outside_matchers() {
    assert_eq!(
        with_bool_comparisons(r#"sum(x{a!~"b|c",d="e>f"}) > 0 and y <= 2 or z != 1"#),
        r#"sum(x{a!~"b|c",d="e>f"}) > bool 0 and y <= bool 2 or z != bool 1"#
    );
    assert_eq!(
        metric_names("rate(kairos_a_total[5m]) / kairos_b"),
        ["kairos_a_total", "kairos_b"]
    );
}

#[test]
#[ignore = "needs Debian's prometheus and the built plugins; scripts/test.sh installs both and runs it"]
fn every_shipped_expression_returns_data_from_a_live_fleet() {
    let monitoring = repo_root().join("deploy/monitoring");
    let rules_file = monitoring.join("kairos.rules.yml");
    let check = Command::new(prometheus_binary("promtool"))
        .args(["check", "rules"])
        .arg(&rules_file)
        .output()
        .unwrap();
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );

    let rules = rules_of(&std::fs::read_to_string(&rules_file).unwrap());
    let dashboard: Value = serde_json::from_str(
        &std::fs::read_to_string(monitoring.join("kairos-fleet.dashboard.json")).unwrap(),
    )
    .unwrap();
    let (panels, variables) = dashboard_expressions(&dashboard);
    assert!(rules.len() >= 6 && panels.len() >= 15, "{panels:?}");

    let mut fleet = LiveFleet::start(4);
    let dir = tempfile::tempdir().unwrap();
    let prometheus = Prometheus::start(dir.path(), fleet.metrics, &rules_file);
    // Enough scrapes for every rate() and deriv() to have two samples, and rounds in them.
    prometheus.wait_for("20 scrapes with rounds answered", || {
        let scrapes = prometheus.query("count_over_time(kairos_driver_alive[5m])");
        let rounds = prometheus.query("increase(kairos_round_latency_seconds_count[1m]) > 0");
        scrapes
            .first()
            .and_then(|s| s["value"][1].as_str()?.parse::<f64>().ok())
            .is_some_and(|n| n >= 20.0)
            && !rounds.is_empty()
    });

    // A worker dies as a crashed one does: the removal is counted and the alert fires.
    fleet.kill_worker(1);
    prometheus.wait_for("KairosWorkerRemoved to fire", || {
        let alerts = get_json(prometheus.addr, "/api/v1/alerts");
        alerts["data"]["alerts"].as_array().is_some_and(|a| {
            a.iter().any(|a| {
                a["labels"]["alertname"] == "KairosWorkerRemoved" && a["state"] == "firing"
            })
        })
    });
    // The surviving worker has run a batch since and been scraped: its round trip is known.
    prometheus.wait_for("the surviving worker's round trip", || {
        !prometheus.query("kairos_worker_rtt_seconds").is_empty()
    });

    let names = get_json(prometheus.addr, "/api/v1/label/__name__/values");
    let scraped: Vec<&str> = names["data"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect();
    let mut failures = Vec::new();
    // An alert's annotations name labels of its series: each answer must carry them.
    for rule in &rules {
        let query = with_bool_comparisons(&rule.expr);
        for series in prometheus.query(&query) {
            for label in &rule.shown_labels {
                if series["metric"].get(label).is_none() {
                    failures.push(format!(
                        "`{query}` answers {series} without the label {label} its annotations show"
                    ));
                }
            }
        }
    }
    let queries = panels
        .iter()
        .map(|e| as_grafana_sends(e))
        .chain(rules.iter().map(|r| with_bool_comparisons(&r.expr)))
        .chain(variables.iter().map(|v| {
            // `label_values(metric, label)`: the metric must have the label.
            let inner = v.trim_start_matches("label_values(").trim_end_matches(')');
            let (metric, label) = inner.split_once(',').unwrap();
            format!("count by ({}) ({})", label.trim(), metric.trim())
        }));
    for query in queries {
        for name in metric_names(&query) {
            if !scraped.contains(&name.as_str()) {
                failures.push(format!("`{query}` reads {name}, which is not exported"));
            }
        }
        if prometheus.query(&query).is_empty() {
            failures.push(format!("`{query}` returned no data"));
        }
    }
    let rules_state = get_json(prometheus.addr, "/api/v1/rules");
    for group in rules_state["data"]["groups"].as_array().unwrap() {
        for rule in group["rules"].as_array().unwrap() {
            if rule["health"] != "ok" {
                failures.push(format!(
                    "rule {} is {}: {}",
                    rule["name"], rule["health"], rule["lastError"]
                ));
            }
        }
    }
    let loaded = rules_state["data"]["groups"][0]["rules"]
        .as_array()
        .map_or(0, Vec::len);
    assert_eq!(loaded, rules.len(), "Prometheus loaded every rule");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
