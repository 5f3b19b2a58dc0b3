//! Settings given beside `kairos.toml` (the command line's flags), applied on top of the file.
//!
//! [`Overrides`] is a plain option struct: the `kairos` binary fills it from its flags, tests and
//! tools fill it directly, and [`Config::load_with`] is the one place that turns a file and its
//! overrides into the checked configuration a server starts from.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use super::{Config, ConfigError, EngineConfig, PluginConfig};

/// What the command line may set on top of the file. `None` (or empty) keeps the file's value.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overrides {
    /// The QUIC listen address.
    pub listen: Option<SocketAddr>,
    /// The openpi endpoint's address (turns it on).
    pub openpi_listen: Option<SocketAddr>,
    /// The metrics endpoint's address (turns it on).
    pub metrics_listen: Option<SocketAddr>,
    /// The data directory.
    pub data_dir: Option<PathBuf>,
    /// The one engine's model; its profile is then measured at start.
    pub model: Option<String>,
    /// The one engine's task tokenizer.
    pub tokenizer: Option<PathBuf>,
    /// The one engine's device (`cpu`, `cuda`, `cuda:N`).
    pub device: Option<String>,
    /// The one engine's precision (`f32`, `bf16`).
    pub precision: Option<String>,
    /// Turns on the one engine's CUDA graphs (`cuda_graphs`); `false` keeps the file's value.
    pub cuda_graphs: bool,
    /// The one engine's local instances (`0`: served by remote workers only).
    pub local_engines: Option<u32>,
    /// A horizon-policy plugin, registered under its file stem and made the default.
    pub horizon_plugin: Option<PathBuf>,
    /// Parameters of the default horizon policy.
    pub horizon_params: Option<BTreeMap<String, f64>>,
    /// A priority-policy plugin, registered under its file stem and made the scheduler's.
    pub priority_plugin: Option<PathBuf>,
    /// Parameters of the priority plugin, `key=value,...`.
    pub priority_params: Option<String>,
}

impl Config {
    /// The configuration of `file` (or the defaults without one) with `overrides` applied,
    /// checked. Errors name the file, or `(command line)`.
    pub fn load_with(file: Option<&Path>, overrides: &Overrides) -> Result<Config, ConfigError> {
        let mut config = match file {
            Some(path) => Config::load(path)?,
            None => Config::default(),
        };
        let source = file.unwrap_or(Path::new("(command line)"));
        overrides.apply(&mut config, source)?;
        config.check(source)?;
        Ok(config)
    }
}

impl Overrides {
    /// Applies the overrides to `config` (read from `source`, for errors).
    pub fn apply(&self, config: &mut Config, source: &Path) -> Result<(), ConfigError> {
        let invalid = |key: &str, reason: String| ConfigError::Invalid {
            path: source.to_path_buf(),
            key: key.to_string(),
            reason,
        };
        if let Some(listen) = self.listen {
            config.listen = listen;
        }
        if let Some(addr) = self.openpi_listen {
            config.openpi.listen = Some(addr);
        }
        if let Some(addr) = self.metrics_listen {
            config.metrics.listen = Some(addr);
        }
        if let Some(dir) = &self.data_dir {
            config.data_dir = dir.clone();
        }
        let engine_flags = self.model.is_some()
            || self.device.is_some()
            || self.precision.is_some()
            || self.cuda_graphs
            || self.tokenizer.is_some();
        if engine_flags {
            if config.engines.len() > 1 {
                return Err(invalid(
                    "engine",
                    format!(
                        "--model, --tokenizer and --device configure the one engine, but the \
                         file lists {} [[engine]] tables: set `model`, `tokenizer` and `device` \
                         in each of them instead",
                        config.engines.len()
                    ),
                ));
            }
            if config.engines.is_empty() {
                config.engines.push(EngineConfig::default());
            }
            let engine = &mut config.engines[0];
            if let Some(model) = &self.model {
                engine.model = model.clone();
                // The file's tokenizer belongs to the file's model.
                engine.tokenizer = None;
            }
            if let Some(tokenizer) = &self.tokenizer {
                engine.tokenizer = Some(tokenizer.clone());
            }
            if let Some(device) = &self.device {
                engine.device = device.clone();
            }
            if let Some(precision) = &self.precision {
                engine.precision = precision.clone();
            }
            if self.cuda_graphs {
                engine.cuda_graphs = true;
            }
            // A profile file describes one model on one device.
            engine.profile = None;
        }
        if let Some(instances) = self.local_engines {
            if config.engines.len() > 1 {
                return Err(invalid(
                    "engine",
                    format!(
                        "--local-engines sets the instances of the one engine, but the file \
                         lists {} [[engine]] tables: set `instances` in each of them instead",
                        config.engines.len()
                    ),
                ));
            }
            if config.engines.is_empty() {
                config.engines.push(EngineConfig::default());
            }
            config.engines[0].instances = instances;
        }
        if let Some(file) = &self.horizon_plugin {
            let plugin = PluginConfig::file(file);
            config.horizon.policy = plugin.name();
            config.horizon.params = BTreeMap::new();
            config.plugins.push(plugin);
        }
        if let Some(params) = &self.horizon_params {
            config.horizon.params = params.clone();
        }
        if let Some(file) = &self.priority_plugin {
            let plugin = PluginConfig::file(file);
            let spec = match &self.priority_params {
                Some(params) if !params.trim().is_empty() => format!("{}:{params}", plugin.name()),
                _ => plugin.name(),
            };
            config.scheduler.policy = spec
                .parse()
                .map_err(|e| invalid("--priority-params", format!("`{spec}`: {e}")))?;
            config.plugins.push(plugin);
        } else if self.priority_params.is_some() {
            return Err(invalid(
                "--priority-params",
                "needs --priority-plugin".to_string(),
            ));
        }
        Ok(())
    }
}
