//! The precompiled-code cache: compiled plugins on disk, keyed by what makes them valid.
//!
//! Compiling a component takes milliseconds for a C plugin and about ten seconds for a Python
//! one; loading precompiled code takes a few milliseconds. But precompiled code is native code
//! that wasmtime maps and runs without validating it again (`Component::deserialize` is
//! `unsafe` for that reason), so the server only ever deserialises files that it wrote itself:
//!
//! - the cache key is the SHA-256 of the component's bytes plus a hash of the engine's
//!   compatibility fingerprint (wasmtime version and every code-affecting setting), so a new
//!   wasmtime or a changed engine config never picks up old code;
//! - next to each `.cwasm` file the server writes an HMAC-SHA256 tag of its bytes, keyed by a
//!   per-installation secret (`secret.key`, 32 random bytes, created with mode 0600 the first
//!   time). A file whose tag does not verify is ignored and recompiled, never deserialised. The
//!   bytes that are verified are the bytes that are deserialised (no re-read in between).
//!
//! Anyone who can read `secret.key` can forge entries, so the directory must belong to the
//! server's user; the server creates it with mode 0700.

use std::fs;
use std::hash::Hasher;
use std::io::Write;
use std::path::{Path, PathBuf};

use hmac::{Hmac, Mac};
use sha2::{Digest, Sha256};
use wasmtime::Engine;
use wasmtime::component::Component;

type HmacSha256 = Hmac<Sha256>;

const SECRET_FILE: &str = "secret.key";
const SECRET_LEN: usize = 32;

/// Why the cache could not be used (the caller then compiles without it, or fails).
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    /// Reading or writing the cache directory failed.
    #[error("plugin cache {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The secret file exists but is not a valid secret.
    #[error("plugin cache secret {0} is corrupt; delete the cache directory to reset it")]
    BadSecret(PathBuf),
}

/// Where a component's code came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CodeSource {
    /// Compiled now, and written to the cache.
    Compiled,
    /// Loaded from a cache file this server wrote.
    Cached,
    /// Compiled now, no cache configured.
    Uncached,
}

/// A directory of precompiled plugins, authenticated with a per-installation secret.
#[derive(Clone)]
pub struct CodeCache {
    dir: PathBuf,
    secret: [u8; SECRET_LEN],
}

impl std::fmt::Debug for CodeCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CodeCache")
            .field("dir", &self.dir)
            .finish_non_exhaustive()
    }
}

impl CodeCache {
    /// Opens (creating if needed) the cache in `dir`.
    pub fn open(dir: impl Into<PathBuf>) -> Result<Self, CacheError> {
        let dir = dir.into();
        create_private_dir(&dir)?;
        let secret = load_or_create_secret(&dir.join(SECRET_FILE))?;
        Ok(CodeCache { dir, secret })
    }

    /// The default location: `$XDG_CACHE_HOME/kairos/plugins`, else `~/.cache/kairos/plugins`.
    pub fn default_dir() -> Option<PathBuf> {
        let base = std::env::var_os("XDG_CACHE_HOME")
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))?;
        Some(base.join("kairos").join("plugins"))
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The cache file for `wasm` under `engine`.
    pub fn entry_path(&self, engine: &Engine, wasm: &[u8]) -> PathBuf {
        self.dir.join(format!("{}.cwasm", cache_key(engine, wasm)))
    }

    /// Loads `wasm`'s compiled code from the cache, or compiles it and stores the result.
    pub fn load_or_compile(
        &self,
        engine: &Engine,
        wasm: &[u8],
    ) -> Result<(Component, CodeSource), wasmtime::Error> {
        let path = self.entry_path(engine, wasm);
        if let Some(component) = self.load(engine, &path) {
            return Ok((component, CodeSource::Cached));
        }
        let code = engine.precompile_component(wasm)?;
        // SAFETY: `code` was produced just now by `precompile_component` of this engine.
        let component = unsafe { Component::deserialize(engine, &code)? };
        if let Err(error) = self.store(&path, &code) {
            tracing::warn!(%error, "cannot write the plugin cache; continuing without it");
        }
        Ok((component, CodeSource::Compiled))
    }

    fn load(&self, engine: &Engine, path: &Path) -> Option<Component> {
        let code = fs::read(path).ok()?;
        let tag = fs::read(tag_path(path)).ok()?;
        if !self.verify(&code, &tag) {
            tracing::warn!(path = %path.display(), "plugin cache entry failed authentication; recompiling");
            return None;
        }
        // SAFETY: the bytes carry a valid HMAC under this installation's secret, so this server
        // wrote them with `precompile_component`; the key includes the engine's compatibility
        // hash, and wasmtime checks its own header again.
        match unsafe { Component::deserialize(engine, &code) } {
            Ok(component) => Some(component),
            Err(error) => {
                tracing::warn!(path = %path.display(), %error, "stale plugin cache entry; recompiling");
                None
            }
        }
    }

    fn store(&self, path: &Path, code: &[u8]) -> Result<(), CacheError> {
        // Write to temporary names and rename, tag last: a reader never sees a tag for a
        // half-written file, and a crash leaves at worst an untagged (ignored) file.
        write_atomically(path, code)?;
        write_atomically(&tag_path(path), &self.tag(code))
    }

    fn mac(&self) -> HmacSha256 {
        // A 32-byte key is always a valid HMAC key.
        <HmacSha256 as Mac>::new_from_slice(&self.secret).unwrap_or_else(|_| unreachable!())
    }

    fn tag(&self, code: &[u8]) -> Vec<u8> {
        let mut mac = self.mac();
        mac.update(code);
        mac.finalize().into_bytes().to_vec()
    }

    fn verify(&self, code: &[u8], tag: &[u8]) -> bool {
        let mut mac = self.mac();
        mac.update(code);
        mac.verify_slice(tag).is_ok()
    }
}

/// Hex SHA-256 of the component bytes, `-`, and 16 hex digits of the engine fingerprint.
pub fn cache_key(engine: &Engine, wasm: &[u8]) -> String {
    let mut fingerprint = Sha256Hasher(Sha256::new());
    std::hash::Hash::hash(&engine.precompile_compatibility_hash(), &mut fingerprint);
    let fingerprint = fingerprint.0.finalize();
    format!(
        "{}-{}",
        hex::encode(Sha256::digest(wasm)),
        hex::encode(&fingerprint[..8])
    )
}

/// Feeds `Hash` output into SHA-256, so the fingerprint is stable across processes (unlike
/// `DefaultHasher`, which is randomly keyed).
struct Sha256Hasher(Sha256);

impl Hasher for Sha256Hasher {
    fn finish(&self) -> u64 {
        let digest = self.0.clone().finalize();
        let mut first = [0u8; 8];
        first.copy_from_slice(&digest[..8]);
        u64::from_le_bytes(first)
    }

    fn write(&mut self, bytes: &[u8]) {
        self.0.update(bytes);
    }
}

fn tag_path(path: &Path) -> PathBuf {
    path.with_extension("cwasm.mac")
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> CacheError + '_ {
    move |source| CacheError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn create_private_dir(dir: &Path) -> Result<(), CacheError> {
    let mut builder = fs::DirBuilder::new();
    builder.recursive(true);
    #[cfg(unix)]
    std::os::unix::fs::DirBuilderExt::mode(&mut builder, 0o700);
    builder.create(dir).map_err(io_error(dir))
}

fn load_or_create_secret(path: &Path) -> Result<[u8; SECRET_LEN], CacheError> {
    match fs::read(path) {
        Ok(bytes) => bytes
            .try_into()
            .map_err(|_| CacheError::BadSecret(path.to_path_buf())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let mut secret = [0u8; SECRET_LEN];
            rand::RngCore::fill_bytes(&mut rand::rng(), &mut secret);
            // Written whole under a private temporary name, then linked into place: the link
            // fails if another server process got there first, and nobody ever reads a
            // half-written secret.
            let tmp = path.with_extension(format!("tmp{}", std::process::id()));
            let mut options = fs::OpenOptions::new();
            options.write(true).create(true).truncate(true);
            #[cfg(unix)]
            std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
            let mut file = options.open(&tmp).map_err(io_error(&tmp))?;
            file.write_all(&secret).map_err(io_error(&tmp))?;
            file.sync_all().map_err(io_error(&tmp))?;
            let linked = fs::hard_link(&tmp, path);
            let _ = fs::remove_file(&tmp);
            match linked {
                Ok(()) => Ok(secret),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    load_or_create_secret(path)
                }
                Err(e) => Err(io_error(path)(e)),
            }
        }
        Err(e) => Err(io_error(path)(e)),
    }
}

fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), CacheError> {
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    fs::write(&tmp, bytes).map_err(io_error(&tmp))?;
    fs::rename(&tmp, path).map_err(io_error(path))
}
