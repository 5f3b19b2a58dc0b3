//! Turning a core WebAssembly module into a policy component.
//!
//! C plugins are compiled by clang to a core module that exports the canonical-ABI functions
//! `wit-bindgen c` generated. This step attaches the `kairos:policy` world (embedded in the
//! server, so it needs no files) and encodes the module as a component, exactly what
//! `wasm-tools component new` does, with the crates wasmtime itself is built from. It is what
//! `kairos plugin componentize` runs, and what `plugins/build.sh` uses.

use wit_component::{ComponentEncoder, StringEncoding};
use wit_parser::Resolve;

use super::PluginKind;

/// The newest released WIT, embedded.
pub const WIT_SOURCE: &str = include_str!("../../../wit/since_v0.1.0/policy.wit");

/// Why a module could not be turned into a component.
#[derive(Debug, thiserror::Error)]
pub enum ComponentizeError {
    /// The input is already a component.
    #[error("the input is already a component")]
    AlreadyComponent,
    /// The input is not a core WebAssembly module.
    #[error("not a WebAssembly module: {0}")]
    NotWasm(String),
    /// The module imports WASI (libc I/O), which plugins cannot use.
    #[error(
        "the module imports `{0}`: it calls libc I/O (printf, files, clocks, ...), which a policy plugin cannot use; remove those calls (or build with componentize-py for Python)"
    )]
    ImportsWasi(String),
    /// Encoding failed (a missing or mistyped export, usually).
    #[error("cannot encode the component: {0}")]
    Encode(String),
}

/// The world name for `kind`.
pub fn world_name(kind: PluginKind) -> &'static str {
    match kind {
        PluginKind::Horizon => "horizon-policy",
        PluginKind::Priority => "priority-policy",
    }
}

/// Encodes `module` as a component implementing `kind`'s world of the embedded WIT.
pub fn componentize(module: &[u8], kind: PluginKind) -> Result<Vec<u8>, ComponentizeError> {
    if wasmparser::Parser::is_component(module) {
        return Err(ComponentizeError::AlreadyComponent);
    }
    if !wasmparser::Parser::is_core_wasm(module) {
        return Err(ComponentizeError::NotWasm(
            "missing the core module header".into(),
        ));
    }
    for payload in wasmparser::Parser::new(0).parse_all(module) {
        let payload = payload.map_err(|e| ComponentizeError::NotWasm(e.to_string()))?;
        if let wasmparser::Payload::ImportSection(imports) = payload {
            for import in imports.into_imports() {
                let import = import.map_err(|e| ComponentizeError::NotWasm(e.to_string()))?;
                if import.module.starts_with("wasi_") {
                    return Err(ComponentizeError::ImportsWasi(format!(
                        "{}::{}",
                        import.module, import.name
                    )));
                }
            }
        }
    }
    let mut resolve = Resolve::default();
    let encode = |e: anyhow::Error| ComponentizeError::Encode(format!("{e:#}"));
    let package = resolve.push_str("policy.wit", WIT_SOURCE).map_err(encode)?;
    let world = resolve
        .select_world(&[package], Some(world_name(kind)))
        .map_err(encode)?;
    let mut module = module.to_vec();
    wit_component::embed_component_metadata(&mut module, &resolve, world, StringEncoding::UTF8)
        .map_err(encode)?;
    ComponentEncoder::default()
        .validate(true)
        .module(&module)
        .map_err(encode)?
        .encode()
        .map_err(encode)
}
