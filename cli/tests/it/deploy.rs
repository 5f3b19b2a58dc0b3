//! What can be checked of the deployment files without a container daemon or a cluster
//! (docs/DEPLOY.md): every path the `Dockerfile` copies from the repository exists, it builds and
//! runs the `kairos` binary, and every subcommand and flag that its `CMD` and the Kubernetes
//! manifests' `args` pass to `kairos` exists in `kairos <subcommand> --help`. The manifests'
//! schemas are validated by `scripts/validate-k8s.sh`.

#![allow(clippy::unwrap_used)] // tests may unwrap (RULES.md)

use std::collections::BTreeSet;
use std::path::Path;
use std::process::Command;

use crate::repo_root;

/// Subcommands and flags the manifests use that are not in this tree yet. Each must be
/// *missing* from `--help`: once it exists, the test fails until it is removed from this list,
/// so nothing here is skipped for longer than the merge.
const NOT_YET_IN_THIS_TREE: &[(&str, &str)] = &[];

/// `kairos <subcommand> --help`, or `None` when the subcommand does not exist.
fn help(subcommand: &str) -> Option<String> {
    let output = Command::new(env!("CARGO_BIN_EXE_kairos"))
        .args([subcommand, "--help"])
        .output()
        .expect("run kairos");
    output
        .status
        .success()
        .then(|| String::from_utf8_lossy(&output.stdout).into_owned())
}

/// Whether `kairos subcommand` has the long option `flag` (`--name`).
fn has_flag(help: &str, flag: &str) -> bool {
    help.split(|c: char| c.is_whitespace() || c == ',' || c == '=' || c == '[')
        .any(|word| word == flag)
}

/// Checks one command line `kairos <subcommand> <args>`; returns the (subcommand, flag) pairs
/// it uses.
fn uses(args: &[String]) -> Vec<(String, String)> {
    let subcommand = args.first().expect("a subcommand").clone();
    let mut used = vec![(subcommand.clone(), String::new())];
    for arg in &args[1..] {
        let flag = arg.split('=').next().unwrap_or(arg);
        assert!(
            flag.starts_with("--"),
            "`{arg}`: flags are written --name=value"
        );
        used.push((subcommand.clone(), flag.to_string()));
    }
    used
}

/// The `args:` lists of the containers in a manifest (block style, one `- item` per line).
fn manifest_args(text: &str) -> Vec<Vec<String>> {
    let mut lists = Vec::new();
    let mut lines = text.lines().peekable();
    while let Some(line) = lines.next() {
        if line.trim() != "args:" {
            continue;
        }
        let mut args = Vec::new();
        while let Some(next) = lines.peek() {
            let item = next.trim();
            if item.starts_with('#') {
                lines.next();
                continue;
            }
            let Some(value) = item.strip_prefix("- ") else {
                break;
            };
            args.push(value.trim_matches('"').to_string());
            lines.next();
        }
        lists.push(args);
    }
    lists
}

fn yaml_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            yaml_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "yaml") {
            out.push(path);
        }
    }
}

#[test]
fn dockerfile_copies_existing_paths_and_runs_existing_flags() {
    let root = repo_root();
    let dockerfile = std::fs::read_to_string(root.join("Dockerfile")).unwrap();
    let mut copied = 0;
    for line in dockerfile.lines() {
        let Some(rest) = line.strip_prefix("COPY ") else {
            continue;
        };
        if rest.starts_with("--from=") {
            continue;
        }
        let parts: Vec<&str> = rest.split_whitespace().collect();
        for source in &parts[..parts.len() - 1] {
            assert!(
                root.join(source).exists(),
                "Dockerfile copies {source}: missing"
            );
            copied += 1;
        }
    }
    assert!(
        copied >= 7,
        "the build stage copies the workspace ({copied} paths)"
    );
    assert!(
        dockerfile.contains("--bin kairos") && dockerfile.contains("target/release/kairos"),
        "it builds the kairos binary"
    );
    let bin = Path::new(env!("CARGO_BIN_EXE_kairos"));
    assert_eq!(bin.file_name().unwrap(), "kairos");
    assert!(dockerfile.contains(r#"ENTRYPOINT ["kairos"]"#));
    let cmd = dockerfile
        .lines()
        .find_map(|l| l.strip_prefix("CMD "))
        .expect("a CMD");
    let args: Vec<String> = serde_json::from_str(cmd).expect("CMD in exec form");
    for (subcommand, flag) in uses(&args) {
        let help = help(&subcommand).unwrap_or_else(|| panic!("no `kairos {subcommand}`"));
        assert!(
            flag.is_empty() || has_flag(&help, &flag),
            "kairos {subcommand} {flag}"
        );
    }
}

#[test]
fn manifests_run_existing_subcommands_and_flags() {
    let mut files = Vec::new();
    yaml_files(&repo_root().join("deploy/kubernetes"), &mut files);
    let mut used = BTreeSet::new();
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        for args in manifest_args(&text) {
            used.extend(uses(&args));
        }
    }
    assert!(used.contains(&("serve".to_string(), "--metrics-listen".to_string())));
    assert!(used.contains(&("worker".to_string(), "--tier".to_string())));
    let pending: BTreeSet<(String, String)> = NOT_YET_IN_THIS_TREE
        .iter()
        .map(|(s, f)| (s.to_string(), f.to_string()))
        .collect();
    for (subcommand, flag) in &used {
        let exists = help(subcommand).is_some_and(|h| flag.is_empty() || has_flag(&h, flag));
        let key = (subcommand.clone(), flag.clone());
        if pending.contains(&key) {
            assert!(
                !exists,
                "`kairos {subcommand} {flag}` exists now: remove it from NOT_YET_IN_THIS_TREE"
            );
        } else {
            assert!(
                exists,
                "the manifests run `kairos {subcommand} {flag}`, which does not exist"
            );
        }
    }
    for key in &pending {
        assert!(
            used.contains(key),
            "{key:?} is listed but no manifest uses it"
        );
    }
}
