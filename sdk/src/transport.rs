//! QUIC transport settings shared by the robot client and the server, tuned for robots on lossy
//! Wi-Fi. The rationale, with measurements, is `docs/PROTOCOL.md` § "Transport".
//!
//! A round is a burst (an observation of 0.1–2 MB up, a 1–10 KB chunk down) followed by silence
//! while the robot executes. quinn's defaults suit a long bulk transfer on a wired path instead:
//! a 3-packet reordering threshold that turns Wi-Fi reordering into spurious losses, CUBIC whose
//! window collapses across the idle gaps, and a 25 ms ACK delay that stretches every small reply.

use std::sync::Arc;
use std::time::Duration;

use quinn::congestion::{BbrConfig, CubicConfig, NewRenoConfig};
use quinn::{AckFrequencyConfig, IdleTimeout, TransportConfig, VarInt};
use rustls::pki_types::{CertificateDer, PrivateKeyDer};

use crate::tls::{ServerTrust, TlsConfigError};

/// Congestion controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Congestion {
    /// BBR: paces at the measured bottleneck rate instead of backing off on every loss, so random
    /// Wi-Fi loss does not halve the window. quinn marks its BBR experimental; the measurements in
    /// `docs/PROTOCOL.md` are what justify it here, and [`Congestion::Cubic`] is one flag away.
    Bbr,
    /// CUBIC, quinn's default.
    Cubic,
    /// NewReno.
    NewReno,
}

/// The knobs of [`tuned_transport_config`], so tests and benchmarks can compare variants.
#[derive(Clone, Debug, PartialEq)]
pub struct TransportTuning {
    /// Congestion controller.
    pub congestion: Congestion,
    /// Largest ACK delay asked of the peer through the ACK-frequency extension (`None` leaves the
    /// peer's own, 25 ms in quinn).
    pub max_ack_delay: Option<Duration>,
    /// Packets that must be acknowledged after a packet before it is declared lost.
    pub packet_threshold: u32,
    /// Time, as a multiple of the RTT, after which an unacknowledged packet is declared lost.
    pub time_threshold: f32,
    /// RTT assumed before the first sample.
    pub initial_rtt: Duration,
    /// Interval between keep-alive packets while the connection is otherwise silent.
    pub keep_alive: Duration,
    /// Silence after which the connection is considered dead.
    pub idle_timeout: Duration,
}

impl Default for TransportTuning {
    fn default() -> TransportTuning {
        TransportTuning {
            congestion: Congestion::Bbr,
            max_ack_delay: Some(Duration::from_millis(1)),
            packet_threshold: 8,
            time_threshold: 1.5,
            initial_rtt: Duration::from_millis(50),
            keep_alive: Duration::from_secs(1),
            idle_timeout: Duration::from_secs(10),
        }
    }
}

impl TransportTuning {
    /// quinn 0.11's own defaults, the baseline the tuning is measured against (keep-alive and idle
    /// timeout kept, since without them a dead server is never noticed).
    pub fn quinn_defaults() -> TransportTuning {
        TransportTuning {
            congestion: Congestion::Cubic,
            max_ack_delay: None,
            packet_threshold: 3,
            time_threshold: 9.0 / 8.0,
            initial_rtt: Duration::from_millis(333),
            ..TransportTuning::default()
        }
    }

    /// The quinn transport config these knobs describe.
    pub fn build(&self) -> TransportConfig {
        let mut config = TransportConfig::default();
        match self.congestion {
            Congestion::Bbr => config.congestion_controller_factory(Arc::new(BbrConfig::default())),
            Congestion::Cubic => {
                config.congestion_controller_factory(Arc::new(CubicConfig::default()))
            }
            Congestion::NewReno => {
                config.congestion_controller_factory(Arc::new(NewRenoConfig::default()))
            }
        };
        if let Some(delay) = self.max_ack_delay {
            let mut ack = AckFrequencyConfig::default();
            ack.max_ack_delay(Some(delay))
                // quinn's advice: one less than the loss-detection packet threshold, so the peer
                // acknowledges reordering just before it would count as loss.
                .reordering_threshold(VarInt::from_u32(self.packet_threshold.saturating_sub(1)));
            config.ack_frequency_config(Some(ack));
        }
        config
            .packet_threshold(self.packet_threshold)
            .time_threshold(self.time_threshold)
            .initial_rtt(self.initial_rtt)
            .keep_alive_interval(Some(self.keep_alive))
            .max_idle_timeout(IdleTimeout::try_from(self.idle_timeout).ok())
            // Kairos sends no unreliable datagrams.
            .datagram_receive_buffer_size(None);
        config
    }
}

/// The transport config both sides use: [`TransportTuning::default`].
pub fn tuned_transport_config() -> TransportConfig {
    TransportTuning::default().build()
}

/// The client's quinn config: tuned transport, TLS per `trust`. A server never opens streams
/// towards a robot in protocol v1, so the client accepts none.
pub fn client_config(
    trust: &ServerTrust,
    tuning: &TransportTuning,
) -> Result<quinn::ClientConfig, TlsConfigError> {
    client_config_with(crate::tls::client_tls(trust)?.config, tuning)
}

pub(crate) fn client_config_with(
    tls: Arc<rustls::ClientConfig>,
    tuning: &TransportTuning,
) -> Result<quinn::ClientConfig, TlsConfigError> {
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(tls)
        .map_err(|error| TlsConfigError::NoInitialSuite(error.to_string()))?;
    let mut transport = tuning.build();
    transport
        .max_concurrent_bidi_streams(VarInt::from_u32(0))
        .max_concurrent_uni_streams(VarInt::from_u32(0));
    let mut config = quinn::ClientConfig::new(Arc::new(crypto));
    config.transport_config(Arc::new(transport));
    Ok(config)
}

/// A remote engine worker's quinn config (`kairos worker`): the same TLS trust as a robot
/// (pinned fingerprint or CA roots) but ALPN `kairos-worker/1`, no 0-RTT (registration is not
/// replay-safe), and room for the scheduler to open a few batch streams towards it.
pub fn worker_client_config(
    trust: &ServerTrust,
    tuning: &TransportTuning,
) -> Result<quinn::ClientConfig, TlsConfigError> {
    let mut tls = crate::tls::client_tls(trust)?.config.as_ref().clone();
    tls.alpn_protocols = vec![crate::protocol::worker::WORKER_ALPN.to_vec()];
    tls.enable_early_data = false;
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(Arc::new(tls))
        .map_err(|error| TlsConfigError::NoInitialSuite(error.to_string()))?;
    let mut transport = tuning.build();
    transport
        .max_concurrent_bidi_streams(VarInt::from_u32(4))
        .max_concurrent_uni_streams(VarInt::from_u32(0));
    let mut config = quinn::ClientConfig::new(Arc::new(crypto));
    config.transport_config(Arc::new(transport));
    Ok(config)
}

/// A server's quinn config: tuned transport, [`crate::tls::server_crypto_config`], connection
/// migration on (robots roam between access points), at most `max_rounds_in_flight` concurrent
/// round streams per connection (each stream is one round or the `Hello`).
pub fn server_config(
    cert_chain: Vec<CertificateDer<'static>>,
    key: PrivateKeyDer<'static>,
    tuning: &TransportTuning,
    max_rounds_in_flight: u32,
) -> Result<quinn::ServerConfig, TlsConfigError> {
    let tls = crate::tls::server_crypto_config(cert_chain, key)?;
    let crypto = quinn::crypto::rustls::QuicServerConfig::try_from(tls)
        .map_err(|error| TlsConfigError::NoInitialSuite(error.to_string()))?;
    let mut transport = tuning.build();
    transport
        .max_concurrent_bidi_streams(VarInt::from_u32(max_rounds_in_flight.max(1)))
        .max_concurrent_uni_streams(VarInt::from_u32(0));
    let mut config = quinn::ServerConfig::with_crypto(Arc::new(crypto));
    config.transport_config(Arc::new(transport)).migration(true);
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tuned_config_carries_the_knobs() {
        let text = format!("{:?}", tuned_transport_config());
        for expected in [
            "packet_threshold: 8",
            "time_threshold: 1.5",
            "initial_rtt: 50ms",
            "keep_alive_interval: Some(1s)",
            "max_ack_delay: Some(1ms)",
            "reordering_threshold: 7",
            "datagram_receive_buffer_size: None",
        ] {
            assert!(text.contains(expected), "{expected} missing from {text}");
        }
        let baseline = format!("{:?}", TransportTuning::quinn_defaults().build());
        assert!(
            baseline.contains("ack_frequency_config: None"),
            "{baseline}"
        );
        assert!(baseline.contains("packet_threshold: 3"), "{baseline}");
    }
}
