//! Online refinement of an engine instance's latency profile from the batch times it really
//! takes.
//!
//! A start-up profile is measured once, on a machine that may be busy: one noisy measurement of
//! batch 2 (3.5x batch 1 where a quiet machine gives 1.8x) capped a server's batches at 1 for
//! its whole life. [`ProfileRefiner`] keeps, per measured batch size, a moving estimate fed by
//! every generation the engine reports, with bounds on how fast and how far it may move:
//!
//! - a measurement moves an estimate by `weight` of the way towards it, and the measurement is
//!   first clamped to within a factor `max_step` of the estimate, so one outlier moves it by at
//!   most `weight x (max_step - 1)` (25% with the defaults) and a noisy minute by a bounded
//!   factor that the next quiet minute undoes at the same rate;
//! - an estimate stays within a factor `bound` of its start-up value;
//! - a batch size the profile's saturation rule no longer allows is never formed, so never
//!   measured: every `probe_every` batches the next larger measured size is allowed for one
//!   batch (a probe), and its time corrects that size's estimate. A batch size switched off by
//!   noise is therefore switched on again once the noise is gone.
//!
//! The rule is pure: time comes in as the measured durations, nothing reads a clock.

use std::time::Duration;

use kairos_engine_types::profile::{EngineProfile, ProfilePoint, saturation_batch};

/// How fast and how far a refined profile may move.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefineConfig {
    /// Fraction of the way a (clamped) measurement moves its estimate, in `(0, 1]`.
    pub weight: f64,
    /// A measurement is first clamped to `[estimate / max_step, estimate x max_step]` (>= 1).
    pub max_step: f64,
    /// An estimate stays within `[start / bound, start x bound]` of its start-up value (>= 1).
    pub bound: f64,
    /// Batches between two probes of the next larger measured batch size (0: never probe).
    pub probe_every: u32,
    /// The saturation rule's minimum throughput gain (see [`saturation_batch`]).
    pub min_gain: f64,
}

impl Default for RefineConfig {
    fn default() -> Self {
        RefineConfig {
            weight: 0.25,
            max_step: 2.0,
            bound: 4.0,
            probe_every: 32,
            min_gain: kairos_engine_types::profile::DEFAULT_MIN_GAIN,
        }
    }
}

/// A profile refined online from measured batch times (see the module documentation).
#[derive(Clone, Debug, PartialEq)]
pub struct ProfileRefiner {
    config: RefineConfig,
    /// The start-up profile (its points bound the estimates, its largest measured batch size
    /// caps the batches).
    start: EngineProfile,
    /// The current estimate per measured batch size, in the start-up profile's order.
    estimate: Vec<ProfilePoint>,
    /// Batches observed since the last probe.
    since_probe: u32,
}

impl ProfileRefiner {
    /// Start from `profile` (its points sorted by batch size). Out-of-range settings are
    /// brought into range (`weight` into `(0, 1]`, `max_step` and `bound` to at least 1).
    pub fn new(profile: &EngineProfile, config: RefineConfig) -> Self {
        let config = RefineConfig {
            weight: if config.weight.is_finite() && config.weight > 0.0 {
                config.weight.min(1.0)
            } else {
                RefineConfig::default().weight
            },
            max_step: finite_at_least_one(config.max_step),
            bound: finite_at_least_one(config.bound),
            ..config
        };
        ProfileRefiner {
            config,
            start: profile.clone(),
            estimate: profile.points.clone(),
            since_probe: 0,
        }
    }

    /// Record one generation of `batch` requests that took `took`.
    pub fn observe(&mut self, batch: u32, took: Duration) {
        self.since_probe = self.since_probe.saturating_add(1);
        if batch > self.max_batch() {
            // A probe was formed: the next one waits another `probe_every` batches.
            self.since_probe = 0;
        }
        let measured_ms = took.as_secs_f64() * 1e3;
        if batch == 0 || !measured_ms.is_finite() || self.estimate.is_empty() {
            return;
        }
        // The measurement says how far off the profile's prediction for this size is; the
        // measured sizes around it share the correction by how close they are.
        let current = self.current_profile();
        let predicted_ms = current.latency(batch).as_secs_f64() * 1e3;
        if predicted_ms <= 0.0 {
            return;
        }
        let ratio = measured_ms / predicted_ms;
        let share: Vec<(usize, f64)> = match self.estimate.iter().position(|p| p.batch >= batch) {
            Some(i) if self.estimate[i].batch == batch || i == 0 => vec![(i, 1.0)],
            Some(i) => {
                let (a, b) = (self.estimate[i - 1].batch, self.estimate[i].batch);
                let f = f64::from(batch - a) / f64::from(b - a);
                vec![(i - 1, 1.0 - f), (i, f)]
            }
            None => vec![(self.estimate.len() - 1, 1.0)],
        };
        let c = self.config;
        for (i, share) in share {
            let est = self.estimate[i].latency_ms;
            let target = (est * ratio).clamp(est / c.max_step, est * c.max_step);
            let moved = est + c.weight * share * (target - est);
            let start = self.start.points[i].latency_ms;
            self.estimate[i].latency_ms = moved.clamp(start / c.bound, start * c.bound);
        }
    }

    /// The largest batch the refined profile is worth forming: the saturation batch of the
    /// current estimates (at most the largest measured batch size: a cap on batches belongs in
    /// the profile as its last point).
    pub fn max_batch(&self) -> u32 {
        saturation_batch(&self.estimate, self.config.min_gain)
            .min(self.cap())
            .max(1)
    }

    /// The largest measured batch size.
    fn cap(&self) -> u32 {
        self.start
            .points
            .iter()
            .map(|p| p.batch)
            .max()
            .unwrap_or(1)
            .max(1)
    }

    /// The largest batch the scheduler may form next: [`Self::max_batch`], or, once
    /// `probe_every` batches have passed since the last probe, the next larger measured size.
    pub fn allowed_batch(&self) -> u32 {
        let max = self.max_batch();
        let due = self.config.probe_every > 0 && self.since_probe >= self.config.probe_every;
        if !due {
            return max;
        }
        self.estimate
            .iter()
            .map(|p| p.batch)
            .find(|&b| b > max && b <= self.cap())
            .unwrap_or(max)
    }

    /// The refined profile: the current estimates and [`Self::max_batch`].
    pub fn current_profile(&self) -> EngineProfile {
        EngineProfile {
            model: self.start.model.clone(),
            device: self.start.device.clone(),
            points: self.estimate.clone(),
            max_batch: self.max_batch(),
        }
    }
}

fn finite_at_least_one(v: f64) -> f64 {
    if v.is_finite() { v.max(1.0) } else { 1.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(v: f64) -> Duration {
        Duration::from_micros((v * 1e3) as u64)
    }

    /// The machine's true times: batch 2 costs 1.8x batch 1, batch 4 3.2x.
    fn quiet(batch: u32) -> Duration {
        ms(match batch {
            1 => 100.0,
            2 => 180.0,
            3 => 250.0,
            _ => 320.0,
        })
    }

    fn profile(points: &[(u32, f64)], max_batch: u32) -> EngineProfile {
        EngineProfile {
            model: "m".into(),
            device: "cpu".into(),
            points: points
                .iter()
                .map(|&(batch, latency_ms)| ProfilePoint { batch, latency_ms })
                .collect(),
            max_batch,
        }
    }

    /// Serve `rounds` batches, each as large as the refiner allows, timed by `time`.
    fn serve(r: &mut ProfileRefiner, rounds: usize, time: impl Fn(u32) -> Duration) {
        for _ in 0..rounds {
            let b = r.allowed_batch();
            r.observe(b, time(b));
        }
    }

    /// The start-up measurement of batch 2 was taken on a busy machine (3.5x batch 1): the
    /// profile allows batches of 1 only. The real batch times, with probes of batch 2, bring
    /// batching back.
    #[test]
    fn a_noisy_start_up_point_does_not_switch_batching_off_for_good() {
        let start = profile(&[(1, 100.0), (2, 350.0), (4, 320.0 * 3.5)], 4);
        let mut r = ProfileRefiner::new(&start, RefineConfig::default());
        assert_eq!(r.max_batch(), 1, "the noisy profile batches nothing");
        serve(&mut r, 400, quiet);
        assert!(r.max_batch() >= 2, "{:?}", r.current_profile());
        let p = r.current_profile();
        assert!((p.points[1].latency_ms - 180.0).abs() < 18.0, "{p:?}");
    }

    /// An injected slow measurement (one batch 10x slower) moves the estimate by at most
    /// `weight x (max_step - 1)` and leaves the batch limit where it was.
    #[test]
    fn one_slow_measurement_moves_the_estimate_a_bounded_step() {
        let start = profile(&[(1, 100.0), (2, 180.0), (4, 320.0)], 4);
        let c = RefineConfig::default();
        let mut r = ProfileRefiner::new(&start, c);
        assert_eq!(r.max_batch(), 4);
        r.observe(2, ms(1800.0));
        let moved = r.current_profile().points[1].latency_ms;
        assert!(moved > 180.0, "the measurement counts");
        assert!(
            moved <= 180.0 * (1.0 + c.weight * (c.max_step - 1.0)) + 1e-9,
            "{moved}"
        );
        assert_eq!(r.max_batch(), 4);
    }

    /// A noisy minute (every batch 3.5x slow) may lower the limit while it lasts; the quiet
    /// minutes after it bring the estimates and the limit back.
    #[test]
    fn a_noisy_minute_is_undone_by_quiet_ones() {
        let start = profile(&[(1, 100.0), (2, 180.0), (4, 320.0)], 4);
        let mut r = ProfileRefiner::new(&start, RefineConfig::default());
        // Batch 1 stays quiet, batches of 2 and 4 are slowed: batching looks worthless.
        serve(&mut r, 300, |b| {
            if b == 1 { quiet(1) } else { quiet(b) * 7 / 2 }
        });
        let noisy = r.current_profile();
        assert!(noisy.points.iter().all(|p| {
            let s = start.points.iter().find(|q| q.batch == p.batch).unwrap();
            p.latency_ms <= s.latency_ms * 4.0 + 1e-9
        }));
        serve(&mut r, 2000, quiet);
        assert_eq!(r.max_batch(), 4, "{:?}", r.current_profile());
    }

    /// Estimates never leave `[start / bound, start x bound]`, whatever is measured, and
    /// nonsense settings are brought into range.
    #[test]
    fn estimates_stay_within_their_bound_and_settings_are_sane() {
        let start = profile(&[(1, 100.0), (2, 180.0)], 2);
        let c = RefineConfig {
            weight: f64::NAN,
            max_step: 0.5,
            bound: f64::INFINITY,
            ..RefineConfig::default()
        };
        let r = ProfileRefiner::new(&start, c);
        assert!(r.config.weight > 0.0 && r.config.max_step >= 1.0 && r.config.bound >= 1.0);
        let mut r = ProfileRefiner::new(&start, RefineConfig::default());
        for _ in 0..1000 {
            r.observe(1, Duration::from_secs(1000));
            r.observe(2, Duration::ZERO);
        }
        let p = r.current_profile();
        assert!((p.points[0].latency_ms - 400.0).abs() < 1e-6, "{p:?}");
        assert!((p.points[1].latency_ms - 45.0).abs() < 1e-6, "{p:?}");
        r.observe(0, Duration::MAX);
        assert_eq!(r.current_profile(), p, "a batch of 0 changes nothing");
    }

    /// A batch size between two measured ones corrects both, by how close it is to each.
    #[test]
    fn an_unmeasured_size_corrects_its_neighbours() {
        let start = profile(&[(1, 100.0), (2, 180.0), (4, 320.0)], 4);
        let mut r = ProfileRefiner::new(&start, RefineConfig::default());
        r.observe(3, ms(375.0)); // 1.5x the profile's 250 ms
        let p = r.current_profile();
        assert_eq!(p.points[0].latency_ms, 100.0);
        assert!(p.points[1].latency_ms > 180.0 && p.points[2].latency_ms > 320.0);
    }
}
