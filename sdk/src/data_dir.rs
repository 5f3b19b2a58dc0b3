//! The robot's side of a server's data directory: the files a local `kairos serve` writes for
//! robots on the same machine (`docs/SERVER.md`, "Data directory"), and reading a robot's
//! credentials (the pin and a token) from them.
//!
//! The server's `DataDir` (crate `kairos-server`) writes these files under the names defined here,
//! so the server, `kairos robot`, the Python package and the tests cannot disagree on them.

use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::tls::Fingerprint;

/// The file holding the fingerprint of the server's certificate, `sha256:<hex>`, one line.
pub const FINGERPRINT_FILE: &str = "fingerprint.txt";

/// The file holding the plaintext tokens of the robots the server generated ([`TokensFile`]).
pub const TOKENS_FILE: &str = "tokens.toml";

/// The data directory a server uses, and robots and workers read, when none is given: relative to
/// the working directory (`kairos_server::config` explains the choice).
pub const DEFAULT_DATA_DIR: &str = "kairos-data";

/// The robot a server started without `[[robot]]` generates a token for.
pub const DEFAULT_ROBOT: &str = "default";

/// `tokens.toml`: the plaintext tokens a local `kairos serve` generates for local robots.
/// Unknown keys are errors, as in `kairos.toml`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokensFile {
    /// One entry per robot.
    #[serde(default, rename = "robot")]
    pub robots: Vec<TokenEntry>,
}

/// One robot in [`TokensFile`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenEntry {
    /// Robot name.
    pub name: String,
    /// The token, as the robot sends it in `Hello`.
    pub token: String,
}

impl TokensFile {
    /// The token of the robot named `name`.
    pub fn token(&self, name: &str) -> Option<&str> {
        self.robots
            .iter()
            .find(|r| r.name == name)
            .map(|r| r.token.as_str())
    }
}

/// Why a robot's credentials could not be read from a data directory.
#[derive(Debug, thiserror::Error)]
pub enum CredentialsError {
    /// A file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// A file's contents are not what the server writes there.
    #[error("{path}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The tokens file has no robot of that name.
    #[error("{path}: no robot named {robot:?}")]
    UnknownRobot {
        /// The tokens file.
        path: PathBuf,
        /// The robot asked for.
        robot: String,
    },
}

fn read_text(path: PathBuf) -> Result<(PathBuf, String), CredentialsError> {
    match fs::read_to_string(&path) {
        Ok(text) => Ok((path, text)),
        Err(source) => Err(CredentialsError::Io { path, source }),
    }
}

/// The pin in `root`'s fingerprint file.
pub fn read_pin(root: &Path) -> Result<Fingerprint, CredentialsError> {
    let (path, text) = read_text(root.join(FINGERPRINT_FILE))?;
    text.trim()
        .parse()
        .map_err(|error| CredentialsError::Invalid {
            path,
            reason: format!("{error}"),
        })
}

/// `root`'s tokens file.
pub fn read_tokens(root: &Path) -> Result<TokensFile, CredentialsError> {
    let (path, text) = read_text(root.join(TOKENS_FILE))?;
    toml::from_str(&text).map_err(|error| CredentialsError::Invalid {
        path,
        reason: error.to_string().trim_end().to_owned(),
    })
}

/// The token of robot `robot` in `root`'s tokens file.
pub fn read_token(root: &Path, robot: &str) -> Result<String, CredentialsError> {
    match read_tokens(root)?.token(robot) {
        Some(token) => Ok(token.to_owned()),
        None => Err(CredentialsError::UnknownRobot {
            path: root.join(TOKENS_FILE),
            robot: robot.to_owned(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_pin_and_a_token_and_names_what_is_missing() {
        let dir = std::env::temp_dir().join(format!("kairos-sdk-data-dir-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        assert!(matches!(
            read_pin(&dir),
            Err(CredentialsError::Io { path, .. }) if path == dir.join(FINGERPRINT_FILE)
        ));
        let pin = format!("sha256:{}", "ab".repeat(32));
        fs::write(dir.join(FINGERPRINT_FILE), format!("{pin}\n")).unwrap();
        assert_eq!(read_pin(&dir).unwrap().to_string(), pin);
        fs::write(
            dir.join(TOKENS_FILE),
            "# comment\n[[robot]]\nname = \"default\"\ntoken = \"t0\"\n",
        )
        .unwrap();
        assert_eq!(read_token(&dir, DEFAULT_ROBOT).unwrap(), "t0");
        assert!(matches!(
            read_token(&dir, "arm-2"),
            Err(CredentialsError::UnknownRobot { robot, .. }) if robot == "arm-2"
        ));
        fs::write(dir.join(FINGERPRINT_FILE), "sha256:zz\n").unwrap();
        assert!(matches!(
            read_pin(&dir),
            Err(CredentialsError::Invalid { .. })
        ));
        fs::remove_dir_all(&dir).unwrap();
    }
}
