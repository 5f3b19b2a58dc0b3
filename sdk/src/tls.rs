//! TLS for Kairos connections: TLS 1.3 only (QUIC allows nothing else), rustls with the *ring*
//! provider, ALPN `kairos/1`.
//!
//! A server started without a CA-issued certificate generates a self-signed one and prints its
//! SHA-256 fingerprint; robots pin that fingerprint ([`ServerTrust::Pinned`]). The pin replaces
//! the chain-of-trust check only: the handshake signature is still verified against the pinned
//! certificate's key, so a peer that merely replays the certificate cannot complete a handshake.
//! Servers with a CA-issued certificate are verified the usual way ([`ServerTrust::Roots`]).

use std::fmt;
use std::path::Path;
use std::str::FromStr;
use std::sync::{Arc, Mutex};

use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::{CryptoProvider, WebPkiSupportedAlgorithms};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName, UnixTime};
use rustls::{CertificateError, DigitallySignedStruct, Error as TlsError, SignatureScheme};
use sha2::{Digest, Sha256};

use crate::protocol::ALPN;

/// The SHA-256 digest of a DER certificate, written `sha256:<64 lowercase hex digits>`.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Fingerprint(pub [u8; 32]);

impl Fingerprint {
    /// The fingerprint of a DER-encoded certificate.
    pub fn of(cert_der: &[u8]) -> Fingerprint {
        Fingerprint(Sha256::digest(cert_der).into())
    }
}

/// `sha256:<hex>` of a DER-encoded certificate (what `kairos serve` prints and robots pin).
pub fn fingerprint(cert_der: &[u8]) -> String {
    Fingerprint::of(cert_der).to_string()
}

impl fmt::Display for Fingerprint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "sha256:{}", hex::encode(self.0))
    }
}

impl fmt::Debug for Fingerprint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(self, f)
    }
}

/// A pin string that is not 64 hex digits, optionally prefixed `sha256:`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("a certificate pin is `sha256:` followed by 64 hex digits, got {0:?}")]
pub struct BadFingerprint(pub String);

/// Parses `sha256:<64 hex digits>`; the bare 64 digits are accepted too (what `sha256sum`
/// prints), since a SHA-256 digest is unambiguous either way. Surrounding whitespace is ignored.
impl FromStr for Fingerprint {
    type Err = BadFingerprint;

    fn from_str(text: &str) -> Result<Fingerprint, BadFingerprint> {
        let bad = || BadFingerprint(text.to_owned());
        let trimmed = text.trim();
        let digits = trimmed.strip_prefix("sha256:").unwrap_or(trimmed);
        let mut bytes = [0u8; 32];
        hex::decode_to_slice(digits, &mut bytes).map_err(|_| bad())?;
        Ok(Fingerprint(bytes))
    }
}

/// How a client decides to trust the server's certificate.
#[derive(Clone, Debug)]
pub enum ServerTrust {
    /// Accept exactly the end-entity certificate with this fingerprint (self-signed servers).
    /// Names and validity dates are not checked: the pin is the trust decision.
    Pinned(Fingerprint),
    /// Verify the chain up to one of these roots and the server name (CA-issued certificates).
    Roots(Arc<rustls::RootCertStore>),
}

impl ServerTrust {
    /// Trust the CA certificates in a PEM file.
    pub fn ca_file(path: &Path) -> Result<ServerTrust, TlsConfigError> {
        let pem = std::fs::read(path).map_err(|source| TlsConfigError::ReadCa {
            path: path.display().to_string(),
            source,
        })?;
        let mut roots = rustls::RootCertStore::empty();
        for cert in CertificateDer::pem_slice_iter(&pem) {
            let cert = cert.map_err(|error| TlsConfigError::BadCa {
                path: path.display().to_string(),
                reason: error.to_string(),
            })?;
            roots.add(cert).map_err(|error| TlsConfigError::BadCa {
                path: path.display().to_string(),
                reason: error.to_string(),
            })?;
        }
        if roots.is_empty() {
            return Err(TlsConfigError::BadCa {
                path: path.display().to_string(),
                reason: "no certificates in the file".to_owned(),
            });
        }
        Ok(ServerTrust::Roots(Arc::new(roots)))
    }
}

/// A TLS configuration that cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum TlsConfigError {
    /// rustls refused the configuration (e.g. a key that does not match the certificate).
    #[error("TLS configuration: {0}")]
    Rustls(#[from] TlsError),
    /// The CA file cannot be read.
    #[error("cannot read CA file {path}: {source}")]
    ReadCa {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The CA file holds no usable certificate.
    #[error("bad CA file {path}: {reason}")]
    BadCa {
        /// The file.
        path: String,
        /// Why.
        reason: String,
    },
    /// The provider lacks the cipher suite QUIC's Initial packets need.
    #[error("QUIC needs TLS_AES_128_GCM_SHA256: {0}")]
    NoInitialSuite(String),
}

/// The *ring* provider every Kairos TLS config uses.
pub fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// Remembers the fingerprint a pinned verifier last refused, so a failed connect can report a
/// typed pin mismatch instead of a TLS alert string.
#[derive(Debug, Default)]
pub(crate) struct PinMismatchSlot(Mutex<Option<Fingerprint>>);

impl PinMismatchSlot {
    fn record(&self, seen: Fingerprint) {
        if let Ok(mut slot) = self.0.lock() {
            *slot = Some(seen);
        }
    }

    /// The fingerprint refused since the last call, if any.
    pub(crate) fn take(&self) -> Option<Fingerprint> {
        self.0.lock().ok().and_then(|mut slot| slot.take())
    }
}

/// Accepts exactly one end-entity certificate, by SHA-256 fingerprint, and verifies the TLS 1.3
/// handshake signature with that certificate's key.
#[derive(Debug)]
pub struct PinnedCertVerifier {
    pin: Fingerprint,
    algorithms: WebPkiSupportedAlgorithms,
    mismatch: Arc<PinMismatchSlot>,
}

impl PinnedCertVerifier {
    /// A verifier for `pin` using `provider`'s signature algorithms.
    pub fn new(pin: Fingerprint, provider: &CryptoProvider) -> PinnedCertVerifier {
        PinnedCertVerifier {
            pin,
            algorithms: provider.signature_verification_algorithms,
            mismatch: Arc::default(),
        }
    }
}

impl ServerCertVerifier for PinnedCertVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, TlsError> {
        let seen = Fingerprint::of(end_entity);
        if seen == self.pin {
            Ok(ServerCertVerified::assertion())
        } else {
            self.mismatch.record(seen);
            Err(TlsError::InvalidCertificate(
                CertificateError::ApplicationVerificationFailure,
            ))
        }
    }

    fn verify_tls12_signature(
        &self,
        _message: &[u8],
        _cert: &CertificateDer<'_>,
        _dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, TlsError> {
        // Only TLS 1.3 is offered; a TLS 1.2 signature here means a confused or hostile peer.
        Err(TlsError::PeerIncompatible(
            rustls::PeerIncompatible::Tls13RequiredForQuic,
        ))
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, TlsError> {
        rustls::crypto::verify_tls13_signature(message, cert, dss, &self.algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.algorithms.supported_schemes()
    }
}

/// A client TLS config plus the slot its pinned verifier reports mismatches to.
pub(crate) struct ClientTls {
    pub(crate) config: Arc<rustls::ClientConfig>,
    pub(crate) mismatch: Option<Arc<PinMismatchSlot>>,
}

/// The rustls client config: TLS 1.3 only, ALPN `kairos/1`, session resumption with early data
/// (0-RTT) enabled. Reuse one config for every connection to a server so that reconnects can
/// resume the TLS session.
pub fn client_crypto_config(trust: &ServerTrust) -> Result<rustls::ClientConfig, TlsConfigError> {
    Ok(client_tls(trust)?.config.as_ref().clone())
}

pub(crate) fn client_tls(trust: &ServerTrust) -> Result<ClientTls, TlsConfigError> {
    let provider = provider();
    let builder = rustls::ClientConfig::builder_with_provider(provider.clone())
        .with_protocol_versions(&[&rustls::version::TLS13])?;
    let (mut config, mismatch) = match trust {
        ServerTrust::Pinned(pin) => {
            let verifier = PinnedCertVerifier::new(*pin, &provider);
            let mismatch = verifier.mismatch.clone();
            let config = builder
                .dangerous()
                .with_custom_certificate_verifier(Arc::new(verifier))
                .with_no_client_auth();
            (config, Some(mismatch))
        }
        ServerTrust::Roots(roots) => {
            let verifier = rustls::client::WebPkiServerVerifier::builder_with_provider(
                roots.clone(),
                provider,
            )
            .build()
            .map_err(|error| TlsConfigError::Rustls(TlsError::General(error.to_string())))?;
            let config = builder.with_webpki_verifier(verifier).with_no_client_auth();
            (config, None)
        }
    };
    config.alpn_protocols = vec![ALPN.to_vec()];
    config.enable_early_data = true;
    Ok(ClientTls {
        config: Arc::new(config),
        mismatch,
    })
}

/// Resumable sessions a server remembers (about 1 KB each); one per robot is enough.
pub const SESSION_CACHE_ENTRIES: usize = 4096;

/// The rustls server config every Kairos server should use: TLS 1.3 only, ALPN `kairos/1`,
/// single-use resumable sessions, and 0-RTT accepted (`max_early_data_size = u32::MAX`, the only
/// non-zero value QUIC allows). See `docs/PROTOCOL.md` § "0-RTT" for why that is safe here.
pub fn server_crypto_config(
    cert_chain: Vec<CertificateDer<'static>>,
    key: PrivateKeyDer<'static>,
) -> Result<rustls::ServerConfig, TlsConfigError> {
    let mut config = rustls::ServerConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .with_no_client_auth()
        .with_single_cert(cert_chain, key)?;
    config.alpn_protocols = vec![ALPN.to_vec()];
    // Stateful resumption, not stateless tickets: rustls accepts early data only then, because a
    // stored session is single-use, so a replayed 0-RTT flight finds nothing to resume.
    config.session_storage = rustls::server::ServerSessionMemoryCache::new(SESSION_CACHE_ENTRIES);
    config.max_early_data_size = u32::MAX;
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_text_round_trips() {
        let fp = Fingerprint::of(b"not really a certificate");
        let text = fp.to_string();
        assert!(text.starts_with("sha256:"));
        assert_eq!(text.len(), 7 + 64);
        assert_eq!(text.parse::<Fingerprint>().unwrap(), fp);
        assert_eq!(
            text.to_uppercase()
                .replace("SHA256:", "sha256:")
                .parse::<Fingerprint>(),
            Ok(fp),
            "hex digits are case-insensitive"
        );
        assert_eq!(fingerprint(b"x"), Fingerprint::of(b"x").to_string());
    }

    #[test]
    fn malformed_pins_are_refused() {
        for bad in ["", "sha256:", "sha256:abcd", "md5:00", &"g".repeat(64)] {
            assert!(bad.parse::<Fingerprint>().is_err(), "{bad:?}");
        }
        let bare = format!("{}\n", "ab".repeat(32));
        assert_eq!(bare.parse::<Fingerprint>(), Ok(Fingerprint([0xab; 32])));
        let long = format!("sha256:{}", "0".repeat(66));
        assert!(long.parse::<Fingerprint>().is_err());
    }
}
