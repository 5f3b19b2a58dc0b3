//! The engine's examples are programs users run by hand: `--help` prints their usage and exits
//! without doing their work (issue #11: every binary answers `--help` with help).

use std::path::PathBuf;
use std::process::Command;

/// An example's executable: `cargo test` (without `--test`) builds every example next to the
/// test binaries, in `target/<profile>/examples/`; `cargo test --test it` alone does not, and then
/// runs whatever example binary an earlier build left there.
fn example(name: &str) -> PathBuf {
    let test_exe = std::env::current_exe().expect("the test binary's path");
    let profile_dir = test_exe
        .parent()
        .and_then(|deps| deps.parent())
        .expect("target/<profile>/deps/<test binary>");
    profile_dir.join("examples").join(name)
}

#[test]
fn the_timing_examples_answer_help_with_their_usage() {
    for (name, usage) in [
        ("expert_timing", "Usage: expert_timing"),
        ("gemm_timing", "Usage: gemm_timing"),
        ("vision_timing", "Usage: vision_timing"),
        ("rtc_timing", "Usage: rtc_timing"),
    ] {
        for flag in ["--help", "-h"] {
            let output = Command::new(example(name))
                .arg(flag)
                .output()
                .unwrap_or_else(|e| {
                    panic!("{name} {flag}: {e} (run `cargo test -p kairos-engine`, which builds the examples)")
                });
            let stdout = String::from_utf8_lossy(&output.stdout);
            assert!(output.status.success(), "{name} {flag}: {output:?}");
            assert!(stdout.contains(usage), "{name} {flag}: {stdout}");
            // The usage and nothing else: no timing line was printed.
            assert!(
                !stdout.contains("median_ms") && !stdout.contains("GFLOP"),
                "{stdout}"
            );
        }
    }
}
