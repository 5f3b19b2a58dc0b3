//! An engine instance behind an emulated network link.

use std::sync::Arc;
use std::time::Duration;

use futures::FutureExt;
use futures::future::BoxFuture;
use kairos_engine::{ActionRequest, EngineProfile, ModelSpec};

use super::{BatchChunks, EngineInstance, PoolError};
use kairos_core::scheduler::Tier;

/// Wraps an instance and adds a fixed round trip to every batch: half before the batch reaches
/// the engine, half after the chunks leave it. This is an **emulation** of a remote (cloud) link
/// for running the edge/cloud placement on one machine — no bytes cross a network. Its name says
/// so (`<inner> (emulated link, rtt N ms)`), and so does every log line and benchmark that uses it.
pub struct EmulatedLinkEngine {
    name: String,
    inner: Arc<dyn EngineInstance>,
    rtt: Duration,
}

impl EmulatedLinkEngine {
    /// `inner` reached over an emulated link with round trip `rtt`; the result is a cloud-tier
    /// instance.
    pub fn new(inner: Arc<dyn EngineInstance>, rtt: Duration) -> EmulatedLinkEngine {
        let name = format!(
            "{} (emulated link, rtt {:.1} ms)",
            inner.name(),
            rtt.as_secs_f64() * 1e3
        );
        EmulatedLinkEngine { name, inner, rtt }
    }
}

impl EngineInstance for EmulatedLinkEngine {
    fn name(&self) -> &str {
        &self.name
    }

    fn spec(&self) -> &ModelSpec {
        self.inner.spec()
    }

    fn profile(&self) -> &EngineProfile {
        self.inner.profile()
    }

    fn tier(&self) -> Tier {
        Tier::Cloud
    }

    fn rtt(&self) -> Duration {
        self.inner.rtt() + self.rtt
    }

    fn run(&self, batch: Vec<ActionRequest>) -> BoxFuture<'static, Result<BatchChunks, PoolError>> {
        let inner = self.inner.clone();
        let half = self.rtt / 2;
        async move {
            tokio::time::sleep(half).await;
            let result = inner.run(batch).await;
            tokio::time::sleep(half).await;
            result
        }
        .boxed()
    }
}

#[cfg(test)]
mod tests {
    use super::super::LocalEngine;
    use super::super::test_model::{LinearFlow, request};
    use super::*;

    #[tokio::test]
    async fn adds_its_round_trip_to_every_batch() {
        let local = Arc::new(LocalEngine::start(
            "m",
            Arc::new(LinearFlow::new()),
            EngineProfile {
                model: "linear-flow".into(),
                device: "cpu".into(),
                points: Vec::new(),
                max_batch: 1,
            },
        ));
        let link = EmulatedLinkEngine::new(local, Duration::from_millis(30));
        assert_eq!(link.name(), "m (emulated link, rtt 30.0 ms)");
        let started = std::time::Instant::now();
        let chunks = link.run(vec![request(1.0, 1)]).await.unwrap();
        assert_eq!(chunks.len(), 1);
        assert!(chunks[0].is_ok());
        assert!(started.elapsed() >= Duration::from_millis(30));
    }
}
