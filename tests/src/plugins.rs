//! Where the tests find the repository and its shipped plugins.

use std::path::PathBuf;

/// The repository's root directory.
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A shipped plugin built by `plugins/build.sh` (`plugins/build/NAME.wasm`); a missing one fails
/// the test with how to build it.
pub fn shipped_plugin(name: &str) -> PathBuf {
    let path = repo_root()
        .join("plugins/build")
        .join(format!("{name}.wasm"));
    assert!(
        path.exists(),
        "{} is missing: build the shipped plugins first with \
         `bash scripts/install-plugin-toolchains.sh && bash plugins/build.sh` (CI's .ci/run does)",
        path.display()
    );
    path
}
