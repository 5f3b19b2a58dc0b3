//! The server's data directory: the one place that names the files `kairos serve` keeps there
//! and reads and writes them. The server, `kairos robot`, the fleet harness and the tests all go
//! through [`DataDir`], so a file cannot be renamed in one of them and not the others.
//!
//! | file | written | contents |
//! |---|---|---|
//! | `cert.der` | first start without `[tls]` | the self-signed certificate (DER) |
//! | `key.der` | with `cert.der`, mode 0600 | its private key (PKCS#8 DER) |
//! | `fingerprint.txt` | every start | `sha256:<hex>` of the certificate in use; robots pin it |
//! | `tokens.toml` | first start without `[[robot]]`, mode 0600 | [`TokensFile`]: generated robots and their plaintext tokens |
//! | `worker-token.txt` | first start, mode 0600 | the token remote engine workers register with (one line); robots' tokens never register a worker, and it never authenticates a robot |
//! | `plugin-cache/` | by the plugin host | authenticated precompiled plugin code |

use std::fs;
use std::path::{Path, PathBuf};

use kairos_sdk::tls::Fingerprint;

use crate::config::{ConfigError, DEFAULT_ROBOT};
use crate::credentials::{generate_token, write_private};

/// A data directory (which need not exist yet) and the names of the files in it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DataDir {
    root: PathBuf,
}

impl DataDir {
    const CERTIFICATE: &'static str = "cert.der";
    const PRIVATE_KEY: &'static str = "key.der";
    const FINGERPRINT: &'static str = kairos_sdk::data_dir::FINGERPRINT_FILE;
    const TOKENS: &'static str = kairos_sdk::data_dir::TOKENS_FILE;
    const PLUGIN_CACHE: &'static str = "plugin-cache";
    const WORKER_TOKEN: &'static str = "worker-token.txt";
    /// Worker tokens start with this, robot tokens with `kairos_`: a token pasted into the
    /// wrong place says what it is.
    pub const WORKER_TOKEN_PREFIX: &'static str = "kairos_worker_";

    /// The data directory at `root`.
    pub fn new(root: impl Into<PathBuf>) -> DataDir {
        DataDir { root: root.into() }
    }

    /// The directory itself.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The self-signed certificate, DER.
    pub fn certificate(&self) -> PathBuf {
        self.root.join(Self::CERTIFICATE)
    }

    /// The self-signed certificate's private key, PKCS#8 DER, owner-only.
    pub fn private_key(&self) -> PathBuf {
        self.root.join(Self::PRIVATE_KEY)
    }

    /// The fingerprint of the certificate in use, one line, for robots to pin.
    pub fn fingerprint(&self) -> PathBuf {
        self.root.join(Self::FINGERPRINT)
    }

    /// The plaintext tokens of generated robots ([`TokensFile`]), owner-only.
    pub fn tokens(&self) -> PathBuf {
        self.root.join(Self::TOKENS)
    }

    /// The token remote engine workers register with, one line, owner-only.
    pub fn worker_token(&self) -> PathBuf {
        self.root.join(Self::WORKER_TOKEN)
    }

    /// Reads the worker token.
    pub fn read_worker_token(&self) -> Result<String, ConfigError> {
        let path = self.worker_token();
        let text = fs::read_to_string(&path).map_err(|source| ConfigError::Io {
            path: path.clone(),
            source,
        })?;
        let token = text.trim();
        if token.is_empty() {
            return Err(ConfigError::Invalid {
                path,
                key: "worker token".into(),
                reason: "the file is empty".into(),
            });
        }
        Ok(token.to_owned())
    }

    /// The worker token, created on first use (a fresh random token, distinct from every robot
    /// token). An existing file is never replaced: workers keep their token across restarts.
    pub fn worker_token_or_generate(&self) -> Result<String, ConfigError> {
        if self.worker_token().exists() {
            return self.read_worker_token();
        }
        fs::create_dir_all(&self.root).map_err(|source| ConfigError::Io {
            path: self.root.clone(),
            source,
        })?;
        let robot_style = generate_token();
        let random = robot_style.trim_start_matches("kairos_");
        let token = format!("{}{random}", Self::WORKER_TOKEN_PREFIX);
        let path = self.worker_token();
        write_private(&path, format!("{token}\n").as_bytes())
            .map_err(|source| ConfigError::Io { path, source })?;
        Ok(token)
    }

    /// The plugin host's cache of precompiled code.
    pub fn plugin_cache(&self) -> PathBuf {
        self.root.join(Self::PLUGIN_CACHE)
    }

    /// Writes the fingerprint file (creating the directory), replacing an older one.
    pub fn write_fingerprint(&self, fingerprint: &str) -> Result<(), ConfigError> {
        fs::create_dir_all(&self.root).map_err(|source| ConfigError::Io {
            path: self.root.clone(),
            source,
        })?;
        let path = self.fingerprint();
        fs::write(&path, format!("{fingerprint}\n"))
            .map_err(|source| ConfigError::Io { path, source })
    }

    /// The pin a robot uses: the fingerprint file's contents.
    pub fn read_pin(&self) -> Result<Fingerprint, ConfigError> {
        let path = self.fingerprint();
        let text = fs::read_to_string(&path).map_err(|source| ConfigError::Io {
            path: path.clone(),
            source,
        })?;
        text.parse().map_err(|error| ConfigError::Invalid {
            path,
            key: "fingerprint".into(),
            reason: format!("{error}"),
        })
    }

    /// Reads the tokens file.
    pub fn read_tokens(&self) -> Result<TokensFile, ConfigError> {
        let path = self.tokens();
        let text = fs::read_to_string(&path).map_err(|source| ConfigError::Io {
            path: path.clone(),
            source,
        })?;
        toml::from_str(&text).map_err(|e| ConfigError::Parse {
            path,
            message: e.to_string().trim_end().to_string(),
        })
    }

    /// The token of the robot named `robot` in the tokens file.
    pub fn token(&self, robot: &str) -> Result<String, ConfigError> {
        match self.read_tokens()?.token(robot) {
            Some(token) => Ok(token.to_owned()),
            None => Err(ConfigError::Invalid {
                path: self.tokens(),
                key: "robot".into(),
                reason: format!("no robot named {robot:?}"),
            }),
        }
    }

    /// The tokens file, created on first use with one robot, [`DEFAULT_ROBOT`], and a fresh
    /// token. An existing file is never replaced: robots keep their tokens across restarts.
    pub fn tokens_or_generate(&self) -> Result<TokensFile, ConfigError> {
        let path = self.tokens();
        if path.exists() {
            return self.read_tokens();
        }
        let file = TokensFile {
            robots: vec![TokenEntry {
                name: DEFAULT_ROBOT.into(),
                token: generate_token(),
            }],
        };
        let body = toml::to_string(&file).map_err(|e| ConfigError::Invalid {
            path: path.clone(),
            key: "robot".into(),
            reason: e.to_string(),
        })?;
        let text = format!(
            "# Tokens of robots generated by `kairos serve` (no [[robot]] in its config).\n\
             # Keep this file private: whoever has a token acts as that robot.\n{body}"
        );
        write_private(&path, text.as_bytes()).map_err(|source| ConfigError::Io {
            path: path.clone(),
            source,
        })?;
        Ok(file)
    }
}

// Robots read these files too (the Python package, `kairos robot`): the SDK owns their format.
pub use kairos_sdk::data_dir::{TokenEntry, TokensFile};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_file_lives_under_the_root_with_its_documented_name() {
        let dir = DataDir::new("state");
        assert_eq!(dir.root(), Path::new("state"));
        let names = [
            dir.certificate(),
            dir.private_key(),
            dir.fingerprint(),
            dir.tokens(),
            dir.plugin_cache(),
            dir.worker_token(),
        ];
        let names: Vec<&str> = names
            .iter()
            .map(|p| {
                assert_eq!(p.parent(), Some(Path::new("state")));
                p.file_name().and_then(|n| n.to_str()).unwrap()
            })
            .collect();
        // docs/SERVER.md ("Data directory") documents these names for operators.
        assert_eq!(
            names,
            [
                "cert.der",
                "key.der",
                "fingerprint.txt",
                "tokens.toml",
                "plugin-cache",
                "worker-token.txt"
            ]
        );
    }

    #[test]
    fn generated_tokens_and_the_pin_round_trip() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = DataDir::new(tmp.path().join("data"));
        let generated = dir.tokens_or_generate().unwrap();
        let token = dir.token(DEFAULT_ROBOT).unwrap();
        assert_eq!(generated.token(DEFAULT_ROBOT), Some(token.as_str()));
        assert!(token.starts_with("kairos_") && token.len() == 7 + 64);
        assert_eq!(dir.read_tokens().unwrap(), generated);
        assert_eq!(
            dir.tokens_or_generate().unwrap(),
            generated,
            "a second start reuses the file"
        );
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = fs::metadata(dir.tokens()).unwrap().permissions().mode();
            assert_eq!(mode & 0o777, 0o600, "tokens are owner-only");
        }

        let pin = Fingerprint([7; 32]);
        dir.write_fingerprint(&pin.to_string()).unwrap();
        assert_eq!(dir.read_pin().unwrap(), pin);
        let other = Fingerprint([9; 32]);
        dir.write_fingerprint(&other.to_string()).unwrap();
        assert_eq!(dir.read_pin().unwrap(), other, "every start rewrites it");
    }

    #[test]
    fn the_worker_token_is_generated_once_private_and_unlike_robot_tokens() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = DataDir::new(tmp.path().join("data"));
        assert!(
            dir.read_worker_token().is_err(),
            "not there before the first start"
        );
        let token = dir.worker_token_or_generate().unwrap();
        assert!(token.starts_with(DataDir::WORKER_TOKEN_PREFIX), "{token}");
        assert_eq!(token.len(), DataDir::WORKER_TOKEN_PREFIX.len() + 64);
        assert_eq!(dir.read_worker_token().unwrap(), token);
        assert_eq!(
            dir.worker_token_or_generate().unwrap(),
            token,
            "kept across starts"
        );
        let robot = dir.tokens_or_generate().unwrap();
        assert_ne!(robot.token(DEFAULT_ROBOT), Some(token.as_str()));
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = fs::metadata(dir.worker_token())
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600, "the worker token is owner-only");
        }
    }

    #[test]
    fn unknown_keys_missing_robots_and_bad_pins_name_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = DataDir::new(tmp.path());
        fs::write(
            dir.tokens(),
            "[[robot]]\nname = \"arm\"\ntoken = \"t\"\nrole = \"admin\"\n",
        )
        .unwrap();
        let error = dir.read_tokens().unwrap_err().to_string();
        assert!(
            error.contains("tokens.toml") && error.contains("role"),
            "{error}"
        );
        fs::write(
            dir.tokens(),
            "[[robot]]\nname = \"default\"\ntoken = \"kairos_abc\"\n\n[[robot]]\nname = \"arm2\"\ntoken = \"kairos_def\"\n",
        )
        .unwrap();
        assert_eq!(dir.token("arm2").unwrap(), "kairos_def");
        let error = dir.token("nobody").unwrap_err().to_string();
        assert!(
            error.contains("tokens.toml") && error.contains("nobody"),
            "{error}"
        );
        let error = dir.read_pin().unwrap_err().to_string();
        assert!(error.contains("fingerprint.txt"), "{error}");
        fs::write(dir.fingerprint(), "sha256:1234\n").unwrap();
        let error = dir.read_pin().unwrap_err().to_string();
        assert!(error.contains("fingerprint.txt"), "{error}");
    }
}
