//! The server's TLS identity and its rustls/QUIC configuration.
//!
//! - TLS 1.3 only (QUIC requires it), *ring* provider, ALPN `kairos/1`.
//! - Certificate: the configured PEM/DER files, or else a self-signed certificate generated on
//!   first start and kept in the data dir ([`DataDir::certificate`], [`DataDir::private_key`] with
//!   mode 0600), reused on every later start so pinned clients keep working. Its SHA-256
//!   fingerprint is printed and written to [`DataDir::fingerprint`]; clients pin it instead of
//!   trusting a CA.
//! - 0-RTT: accepted. Resumption is *stateful* (rustls' in-memory session cache, no stateless
//!   ticketer), which makes every TLS 1.3 ticket single-use: a replayed ClientHello finds its
//!   ticket already consumed and falls back to a full handshake with its early data rejected. So
//!   0-RTT data is never acted on twice. As defence in depth the protocol is idempotent where a
//!   replay could land anyway: rounds are keyed by `(task, round)` and a repeated round id
//!   attaches to the round in flight or gets its cached reply. Restarting the server forgets the
//!   cache, so tickets from before a restart simply fall back to a full handshake.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::server::ServerSessionMemoryCache;
use rustls_pki_types::pem::PemObject;
use rustls_pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

use crate::config::{Config, ConfigError};
use crate::credentials::write_private;
use crate::data_dir::DataDir;

/// Names the generated certificate is valid for. Clients pin the fingerprint, so the names only
/// matter to clients that verify them; these cover local use.
const SELF_SIGNED_NAMES: [&str; 3] = ["localhost", "127.0.0.1", "::1"];

/// Why the TLS identity or configuration could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// Reading or writing a file failed.
    #[error(transparent)]
    File(#[from] ConfigError),
    /// A PEM file holds no certificate or no key, or is malformed.
    #[error("{}: {reason}", .path.display())]
    Pem {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Generating the self-signed certificate failed.
    #[error("cannot generate a self-signed certificate: {0}")]
    Generate(#[from] rcgen::Error),
    /// rustls refused the certificate or key.
    #[error("TLS configuration: {0}")]
    Rustls(#[from] rustls::Error),
    /// The provider lacks the cipher suite QUIC needs for its initial packets.
    #[error("QUIC TLS configuration: {0}")]
    Quic(#[from] quinn::crypto::rustls::NoInitialCipherSuite),
}

/// The certificate chain and key the server presents.
#[derive(Debug)]
pub struct ServerIdentity {
    /// Leaf first.
    pub cert_chain: Vec<CertificateDer<'static>>,
    /// The leaf's private key.
    pub key: PrivateKeyDer<'static>,
    /// SHA-256 of the leaf certificate, `sha256:<lower-case hex>`.
    pub fingerprint: String,
    /// Where the leaf certificate came from.
    pub cert_path: PathBuf,
    /// True when it was generated during this call (first start).
    pub generated: bool,
}

/// SHA-256 fingerprint of a DER certificate, `sha256:<hex>`: what clients pin.
pub fn fingerprint(cert_der: &[u8]) -> String {
    kairos_sdk::tls::fingerprint(cert_der)
}

/// Loads the configured certificate, or the one in the data dir, generating it on first start.
/// Writes the data dir's fingerprint file either way.
pub fn load_or_generate(config: &Config) -> Result<ServerIdentity, TlsError> {
    let data_dir = DataDir::new(&config.data_dir);
    let identity = match (&config.tls.cert, &config.tls.key) {
        (Some(cert), Some(key)) => ServerIdentity::from_files(cert, key)?,
        _ => ServerIdentity::self_signed_in(&data_dir)?,
    };
    data_dir.write_fingerprint(&identity.fingerprint)?;
    Ok(identity)
}

impl ServerIdentity {
    /// Reads a certificate chain and key, PEM or (by `.der` extension) DER.
    pub fn from_files(cert: &Path, key: &Path) -> Result<ServerIdentity, TlsError> {
        let cert_chain = if is_der(cert) {
            vec![CertificateDer::from(read(cert)?)]
        } else {
            CertificateDer::pem_file_iter(cert)
                .and_then(|certs| certs.collect::<Result<Vec<_>, _>>())
                .map_err(|e| pem_error(cert, e))?
        };
        let key_der = if is_der(key) {
            PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(read(key)?))
        } else {
            PrivateKeyDer::from_pem_file(key).map_err(|e| pem_error(key, e))?
        };
        let leaf = cert_chain.first().ok_or_else(|| TlsError::Pem {
            path: cert.to_path_buf(),
            reason: "no certificate in the file".into(),
        })?;
        Ok(ServerIdentity {
            fingerprint: fingerprint(leaf),
            cert_chain,
            key: key_der,
            cert_path: cert.to_path_buf(),
            generated: false,
        })
    }

    /// The self-signed identity kept in `data_dir`, generated if absent.
    pub fn self_signed_in(data_dir: &DataDir) -> Result<ServerIdentity, TlsError> {
        let cert_path = data_dir.certificate();
        let key_path = data_dir.private_key();
        if cert_path.exists() && key_path.exists() {
            let mut identity = ServerIdentity::from_files(&cert_path, &key_path)?;
            identity.generated = false;
            return Ok(identity);
        }
        let names: Vec<String> = SELF_SIGNED_NAMES.iter().map(|s| s.to_string()).collect();
        let certified = rcgen::generate_simple_self_signed(names)?;
        let cert_der = certified.cert.der().clone();
        let key_der = certified.signing_key.serialize_der();
        // Key first: a certificate without its key on disk would be unusable next start.
        write_private(&key_path, &key_der).map_err(|source| ConfigError::Io {
            path: key_path.clone(),
            source,
        })?;
        fs::write(&cert_path, cert_der.as_ref()).map_err(|source| ConfigError::Io {
            path: cert_path.clone(),
            source,
        })?;
        Ok(ServerIdentity {
            fingerprint: fingerprint(&cert_der),
            cert_chain: vec![cert_der],
            key: PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(key_der)),
            cert_path,
            generated: true,
        })
    }

    /// The QUIC server crypto: TLS 1.3 only, ALPN `kairos/1` (robots) and `kairos-worker/1`
    /// (remote engine workers, refused unless `[workers] enabled`), 0-RTT with single-use tickets
    /// (see the module docs). `sessions` bounds the resumption cache (one entry per ticket).
    pub fn quic_crypto(
        &self,
        sessions: usize,
    ) -> Result<quinn::crypto::rustls::QuicServerConfig, TlsError> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut tls = rustls::ServerConfig::builder_with_provider(provider)
            .with_protocol_versions(&[&rustls::version::TLS13])?
            .with_no_client_auth()
            .with_single_cert(self.cert_chain.clone(), self.key.clone_key())?;
        tls.alpn_protocols = vec![
            kairos_sdk::protocol::ALPN.to_vec(),
            kairos_sdk::protocol::worker::WORKER_ALPN.to_vec(),
        ];
        // QUIC allows only 0 or u32::MAX; MAX enables 0-RTT.
        tls.max_early_data_size = u32::MAX;
        // Stateful resumption: single-use tickets are what makes 0-RTT replay-safe.
        tls.session_storage = ServerSessionMemoryCache::new(sessions.max(16));
        Ok(quinn::crypto::rustls::QuicServerConfig::try_from(tls)?)
    }
}

fn is_der(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("der"))
}

fn read(path: &Path) -> Result<Vec<u8>, TlsError> {
    fs::read(path).map_err(|source| {
        TlsError::File(ConfigError::Io {
            path: path.to_path_buf(),
            source,
        })
    })
}

fn pem_error(path: &Path, error: rustls_pki_types::pem::Error) -> TlsError {
    TlsError::Pem {
        path: path.to_path_buf(),
        reason: error.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn self_signed_identity_is_generated_once_and_reused() {
        let dir = tempfile::tempdir().unwrap();
        let config = Config {
            data_dir: dir.path().join("data"),
            ..Config::default()
        };
        let first = load_or_generate(&config).unwrap();
        assert!(first.generated);
        assert!(first.fingerprint.starts_with("sha256:"));
        assert_eq!(first.fingerprint.len(), 7 + 64);
        let data_dir = DataDir::new(&config.data_dir);
        let on_disk = fs::read_to_string(data_dir.fingerprint()).unwrap();
        assert_eq!(on_disk.trim(), first.fingerprint);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = fs::metadata(data_dir.private_key())
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600, "the private key is owner-only");
        }
        let second = load_or_generate(&config).unwrap();
        assert!(!second.generated);
        assert_eq!(second.fingerprint, first.fingerprint);
        second.quic_crypto(64).unwrap();
    }

    #[test]
    fn pem_files_load_and_bad_ones_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let certified = rcgen::generate_simple_self_signed(vec!["example".to_string()]).unwrap();
        let cert = dir.path().join("c.pem");
        let key = dir.path().join("k.pem");
        fs::write(&cert, certified.cert.pem()).unwrap();
        fs::write(&key, certified.signing_key.serialize_pem()).unwrap();
        let identity = ServerIdentity::from_files(&cert, &key).unwrap();
        assert_eq!(identity.fingerprint, fingerprint(certified.cert.der()));
        identity.quic_crypto(64).unwrap();

        let empty = dir.path().join("empty.pem");
        fs::write(&empty, "not a pem file").unwrap();
        let err = ServerIdentity::from_files(&empty, &key).unwrap_err();
        assert!(err.to_string().contains("empty.pem"), "{err}");
    }
}
