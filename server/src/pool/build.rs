//! The engine pool `[[engine]]` sections describe, and [`ModelSchemes`]: model specs a caller
//! adds to those the engine crate resolves.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use kairos_engine::profile::{
    DEFAULT_MIN_GAIN, MeasureEvent, MeasureOptions, measure, saturation_batch,
};
use kairos_engine::{
    ActionModel, EngineError, EngineOptions, EngineProfile, ProfilePoint, StagePaths,
};

use super::{EmulatedLinkEngine, EngineInstance, EnginePool, LocalEngine, PoolBuildError};
use crate::config::EngineConfig;
use kairos_core::scheduler::Tier;

/// Timed generations per batch size when a profile is measured at start (after one warm-up);
/// the median is kept.
const START_PROFILE_ITERATIONS: usize = 3;

/// Why the configured engines could not be started.
#[derive(Debug, thiserror::Error)]
pub enum PoolConfigError {
    /// The model could not be loaded.
    #[error("engine[{index}]: loading `{model}`: {source}")]
    Model {
        /// Which `[[engine]]`.
        index: usize,
        /// Its `model`.
        model: String,
        /// The engine's error (boxed: Candle's errors are large, and this one is rare).
        source: Box<EngineError>,
    },
    /// The profile file could not be read.
    #[error("engine[{index}]: profile {}: {reason}", .path.display())]
    Profile {
        /// Which `[[engine]]`.
        index: usize,
        /// The file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
    /// Measuring the profile failed.
    #[error("engine[{index}]: measuring the profile of `{model}`: {source}")]
    Measure {
        /// Which `[[engine]]`.
        index: usize,
        /// Its `model`.
        model: String,
        /// The engine's error (boxed, as above).
        source: Box<EngineError>,
    },
    /// The instances do not form a pool.
    #[error(transparent)]
    Pool(#[from] PoolBuildError),
}

/// What [`build_pool`] reports while it works (for a progress display).
#[derive(Clone, Debug, PartialEq)]
pub enum BuildEvent {
    /// Loading engine `index`'s model.
    Loading {
        /// Which `[[engine]]`.
        index: usize,
        /// Its `model`.
        model: String,
    },
    /// Measuring its profile: one timed generation finished.
    Measured {
        /// Which `[[engine]]`.
        index: usize,
        /// Batch size of the run.
        batch: u32,
        /// Timed runs done so far out of `total`.
        done: usize,
        /// Timed runs in all.
        total: usize,
    },
    /// Its instances are running.
    Ready {
        /// Which `[[engine]]`.
        index: usize,
        /// Its profile.
        profile: EngineProfile,
        /// The path each stage of its model runs on, when the model says.
        paths: Option<StagePaths>,
    },
}

/// Starts every configured engine instance (an empty list means one edge instance of the
/// built-in model). An engine with `instances = 0` (`kairos serve --local-engines 0`) is loaded
/// only for its spec, the shapes remote workers must match; it is not profiled and runs
/// nothing. Blocking: loading and profiling run models; call it off the async runtime.
pub fn build_pool(
    engines: &[EngineConfig],
    schemes: &ModelSchemes,
    mut progress: impl FnMut(BuildEvent),
) -> Result<EnginePool, PoolConfigError> {
    let default = [EngineConfig::default()];
    let engines = if engines.is_empty() {
        &default[..]
    } else {
        engines
    };
    let mut instances: Vec<Arc<dyn EngineInstance>> = Vec::new();
    let mut site_spec = None;
    for (index, config) in engines.iter().enumerate() {
        progress(BuildEvent::Loading {
            index,
            model: config.model.clone(),
        });
        let failed = |source| PoolConfigError::Model {
            index,
            model: config.model.clone(),
            source: Box::new(source),
        };
        let options = config.options().map_err(failed)?;
        let model: Arc<dyn ActionModel> = schemes
            .resolve(&config.model, config.tokenizer.as_deref(), &options)
            .map_err(failed)?
            .into();
        site_spec.get_or_insert_with(|| model.spec().clone());
        if config.instances == 0 {
            continue;
        }
        let mut profile = match &config.profile {
            Some(path) => read_profile(index, path)?,
            None => measure_at_start(index, config, model.as_ref(), &options, &mut progress)?,
        };
        if let Some(cap) = config.max_batch {
            profile.max_batch = profile.max_batch.min(cap).max(1);
            // The scheduler's online refinement never forms batches larger than the profile's
            // largest point: the points past the cap go.
            if profile.points.iter().any(|p| p.batch <= cap) {
                profile.points.retain(|p| p.batch <= cap);
            }
        }
        progress(BuildEvent::Ready {
            index,
            profile: profile.clone(),
            paths: model.paths(),
        });
        for i in 0..config.instances {
            let name = format!("{}-{index}.{i}", tier_name(config.tier));
            let local: Arc<dyn EngineInstance> =
                Arc::new(LocalEngine::start(name, model.clone(), profile.clone()));
            instances.push(match config.tier {
                Tier::Edge => local,
                Tier::Cloud => Arc::new(EmulatedLinkEngine::new(local, config.rtt())),
            });
        }
    }
    let spec = site_spec.ok_or(PoolBuildError::Empty)?;
    Ok(EnginePool::with_spec(spec, instances)?)
}

/// Resolves a model spec `scheme:REST` of a scheme the caller registered, taking the
/// `--tokenizer` argument and the engine options.
pub type ResolveModel = dyn Fn(&str, Option<&Path>, &EngineOptions) -> Result<Box<dyn ActionModel>, EngineError>
    + Send
    + Sync;

/// Model specs beyond the engine crate's (`builtin`, `builtin:<preset>`, a checkpoint folder):
/// `scheme:REST`, loaded by a function its caller registers. A tool with models of its own (the
/// closed-loop bench's `horizon-flow:DIR`) registers them here, so serving never imports the
/// tool. `REST` is a path; `kairos.toml` resolves it against the file's folder
/// ([`Config::load`](crate::config::Config::load)).
#[derive(Clone, Default)]
pub struct ModelSchemes {
    schemes: Vec<(String, Arc<ResolveModel>)>,
}

impl std::fmt::Debug for ModelSchemes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(self.schemes.iter().map(|(scheme, _)| scheme))
            .finish()
    }
}

impl ModelSchemes {
    /// Only the engine crate's models.
    pub fn new() -> ModelSchemes {
        ModelSchemes::default()
    }

    /// Specs `scheme:REST` are loaded by `resolve(REST, tokenizer, options)` (a later
    /// registration of the same scheme replaces the earlier).
    pub fn register(
        &mut self,
        scheme: &str,
        resolve: impl Fn(
            &str,
            Option<&Path>,
            &EngineOptions,
        ) -> Result<Box<dyn ActionModel>, EngineError>
        + Send
        + Sync
        + 'static,
    ) -> &mut ModelSchemes {
        self.schemes.retain(|(s, _)| s != scheme);
        self.schemes.push((scheme.to_string(), Arc::new(resolve)));
        self
    }

    /// Loads the model `name` names: a registered scheme's, or whatever the engine crate
    /// resolves, with `tokenizer` for a SmolVLA checkpoint (`None`: the `tokenizer.json` beside
    /// it; a model that reads no text refuses one).
    pub fn resolve(
        &self,
        name: &str,
        tokenizer: Option<&Path>,
        options: &EngineOptions,
    ) -> Result<Box<dyn ActionModel>, EngineError> {
        for (scheme, resolve) in &self.schemes {
            if let Some(rest) = name
                .strip_prefix(scheme.as_str())
                .and_then(|r| r.strip_prefix(':'))
            {
                return resolve(rest, tokenizer, options);
            }
        }
        kairos_engine::resolve_model_with(name, tokenizer, options)
    }
}

fn tier_name(tier: Tier) -> &'static str {
    match tier {
        Tier::Edge => "edge",
        Tier::Cloud => "cloud",
    }
}

fn read_profile(index: usize, path: &std::path::Path) -> Result<EngineProfile, PoolConfigError> {
    let error = |reason: String| PoolConfigError::Profile {
        index,
        path: path.to_path_buf(),
        reason,
    };
    let text = std::fs::read_to_string(path).map_err(|e| error(e.to_string()))?;
    let profile: EngineProfile = serde_json::from_str(&text).map_err(|e| error(e.to_string()))?;
    if profile.points.is_empty() {
        return Err(error("the profile has no points".into()));
    }
    Ok(profile)
}

/// Batch sizes measured at start: powers of two up to `max`, and `max` itself.
fn start_batches(max: u32) -> Vec<u32> {
    let mut batches: Vec<u32> = std::iter::successors(Some(1u32), |b| b.checked_mul(2))
        .take_while(|&b| b < max)
        .collect();
    batches.push(max.max(1));
    batches
}

/// Measures batch sizes 1, 2, 4, … up to `profile_max_batch`, stopping at the first size whose
/// throughput gain over the best so far is below the saturation rule's `min_gain`: beyond the
/// saturation point larger batches only cost start-up time (a CPU model that does not batch
/// stops after batch 2). The profile's `max_batch` is the engine crate's saturation rule over
/// the measured points.
fn measure_at_start(
    index: usize,
    config: &EngineConfig,
    model: &dyn ActionModel,
    options: &EngineOptions,
    progress: &mut impl FnMut(BuildEvent),
) -> Result<EngineProfile, PoolConfigError> {
    let failed = |source: EngineError| PoolConfigError::Measure {
        index,
        model: config.model.clone(),
        source: Box::new(source),
    };
    let device = format!(
        "{} (measured at start)",
        options.describe().map_err(failed)?
    );
    let batches = start_batches(config.profile_max_batch);
    let total = batches.len() * START_PROFILE_ITERATIONS;
    let throughput = |p: &ProfilePoint| f64::from(p.batch) / p.latency_ms.max(f64::MIN_POSITIVE);
    let mut points: Vec<ProfilePoint> = Vec::new();
    let mut done = 0;
    for batch in batches {
        let measure_options = MeasureOptions {
            batches: vec![batch],
            iterations: START_PROFILE_ITERATIONS,
            device: device.clone(),
            min_gain: DEFAULT_MIN_GAIN,
        };
        let measured = measure(model, &measure_options, |event| {
            if let MeasureEvent::Run { batch, .. } = event {
                done += 1;
                progress(BuildEvent::Measured {
                    index,
                    batch,
                    done,
                    total,
                });
            }
        })
        .map_err(failed)?;
        let Some(&point) = measured.points.first() else {
            break;
        };
        let best = points.iter().map(throughput).fold(0.0, f64::max);
        points.push(point);
        if best > 0.0 && throughput(&point) <= best * (1.0 + DEFAULT_MIN_GAIN) {
            break;
        }
    }
    Ok(EngineProfile {
        model: model.spec().name.clone(),
        device,
        max_batch: saturation_batch(&points, DEFAULT_MIN_GAIN),
        points,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_registered_scheme_is_resolved_before_the_engine_crate() {
        let mut schemes = ModelSchemes::new();
        schemes.register("echo", |rest, tokenizer, _| {
            Err(EngineError::InvalidInput(format!(
                "echo asked for `{rest}` with tokenizer {tokenizer:?}"
            )))
        });
        let error = schemes
            .resolve(
                "echo:dir/x",
                Some(Path::new("t.json")),
                &EngineOptions::default(),
            )
            .err()
            .expect("the registered resolver answered");
        assert!(
            error
                .to_string()
                .contains("`dir/x` with tokenizer Some(\"t.json\")"),
            "{error}"
        );
        // Another scheme, or the bare name, goes to the engine crate.
        assert!(
            schemes
                .resolve("echoes:x", None, &EngineOptions::default())
                .is_err()
        );
        let builtin = schemes
            .resolve("builtin", None, &EngineOptions::default())
            .unwrap();
        let default = kairos_engine::default_model(&EngineOptions::default()).unwrap();
        assert_eq!(builtin.spec().name, default.spec().name);
    }

    #[test]
    fn start_batches_are_powers_of_two_up_to_the_maximum() {
        assert_eq!(start_batches(1), vec![1]);
        assert_eq!(start_batches(8), vec![1, 2, 4, 8]);
        assert_eq!(start_batches(12), vec![1, 2, 4, 8, 12]);
    }

    #[test]
    fn configured_engines_start_with_their_profile_tier_and_cap() {
        let dir = tempfile::tempdir().unwrap();
        let profile = EngineProfile {
            model: "flow-head-small".into(),
            device: "test".into(),
            points: vec![kairos_engine::ProfilePoint {
                batch: 1,
                latency_ms: 5.0,
            }],
            max_batch: 16,
        };
        let path = dir.path().join("p.json");
        std::fs::write(&path, serde_json::to_string(&profile).unwrap()).unwrap();
        let engines = [
            EngineConfig {
                profile: Some(path.clone()),
                instances: 2,
                max_batch: Some(4),
                ..EngineConfig::default()
            },
            EngineConfig {
                profile: Some(path),
                tier: Tier::Cloud,
                rtt_ms: 20.0,
                ..EngineConfig::default()
            },
        ];
        let mut events = Vec::new();
        let pool = build_pool(&engines, &ModelSchemes::new(), |e| events.push(e)).unwrap();
        let specs = pool.specs();
        assert_eq!(specs.len(), 3);
        assert_eq!(specs[0].profile.max_batch, 4, "max_batch caps the profile");
        assert_eq!(specs[2].tier, Tier::Cloud);
        assert_eq!(specs[2].rtt, std::time::Duration::from_millis(20));
        assert!(specs[2].name.contains("emulated link"));
        assert_eq!(
            events
                .iter()
                .filter(|e| matches!(e, BuildEvent::Ready { .. }))
                .count(),
            2
        );

        let bad = [EngineConfig {
            model: "builtin:nope".into(),
            ..EngineConfig::default()
        }];
        let err = build_pool(&bad, &ModelSchemes::new(), |_| {}).unwrap_err();
        assert!(err.to_string().contains("builtin:nope"), "{err}");
    }

    #[test]
    fn device_kernels_and_threads_reach_the_engine() {
        let engines = [EngineConfig {
            kernels: "portable".into(),
            threads: 1,
            profile_max_batch: 1,
            ..EngineConfig::default()
        }];
        let pool = build_pool(&engines, &ModelSchemes::new(), |_| {}).unwrap();
        let device = &pool.specs()[0].profile.device;
        assert!(
            device.contains("Portable") && device.contains("1 threads"),
            "the profile measured at start names the kernels it ran: {device}"
        );
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn cuda_without_the_feature_is_a_clear_error() {
        let engines = [EngineConfig {
            device: "cuda:0".into(),
            ..EngineConfig::default()
        }];
        let err = build_pool(&engines, &ModelSchemes::new(), |_| {})
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("engine[0]") && err.contains("--features cuda"),
            "{err}"
        );
    }
}
