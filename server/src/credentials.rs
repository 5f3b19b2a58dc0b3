//! Robot credentials: token hashes, generated tokens, and owner-only files for secrets. The
//! configuration (`config`), the data directory (`data_dir`) and the transport use these.

use std::fs;
use std::io::Write;
use std::path::Path;

use sha2::{Digest, Sha256};

/// A robot the server accepts, with the token hash to compare against.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RobotCredential {
    /// Robot name.
    pub name: String,
    /// SHA-256 of its token.
    pub token_hash: [u8; 32],
}

/// SHA-256 of a token's UTF-8 bytes.
pub fn hash_token(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

/// Parses 64 hex digits (either case) into a hash.
pub fn parse_token_hash(hex_digits: &str) -> Option<[u8; 32]> {
    let bytes = hex::decode(hex_digits.trim()).ok()?;
    bytes.try_into().ok()
}

/// A fresh random token: 32 bytes from the OS-seeded CSPRNG, hex encoded, with a `kairos_`
/// prefix so a leaked one is recognisable.
pub fn generate_token() -> String {
    let bytes: [u8; 32] = rand::random();
    format!("kairos_{}", hex::encode(bytes))
}

/// Creates `path` (and its parent directories) with owner-only permissions and writes `bytes`.
/// Fails if the file exists, so a secret is never silently replaced.
pub fn write_private(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        fs::create_dir_all(parent)?;
    }
    let mut options = fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o600);
    }
    let mut file = options.open(path)?;
    file.write_all(bytes)?;
    file.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_hash_matches_sha256sum() {
        // printf %s test | sha256sum
        assert_eq!(
            hex::encode(hash_token("test")),
            "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"
        );
        assert_eq!(
            parse_token_hash("9F86D081884C7D659A2FEAA0C55AD015A3BF4F1B2B0B822CD15D6C15B0F00A08"),
            Some(hash_token("test"))
        );
    }
}
