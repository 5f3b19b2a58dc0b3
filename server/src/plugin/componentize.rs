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
use super::bindings::WitVersion;

/// Every released WIT, embedded, oldest first; a core module is encoded against the version
/// whose export names it carries (`kairos:policy/priority@0.2.0#rank`).
pub const WIT_SOURCES: &[(WitVersion, &str)] = &[
    (
        super::bindings::since_v0_1_0::VERSION,
        include_str!("../../../wit/since_v0.1.0/policy.wit"),
    ),
    (
        super::bindings::since_v0_2_0::VERSION,
        include_str!("../../../wit/since_v0.2.0/policy.wit"),
    ),
    (
        super::bindings::since_v0_3_0::VERSION,
        include_str!("../../../wit/since_v0.3.0/policy.wit"),
    ),
];

/// The newest released WIT, embedded: what new plugins should target.
pub const WIT_SOURCE: &str = WIT_SOURCES[WIT_SOURCES.len() - 1].1;

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
    /// The module exports no function of a released `kairos:policy` version.
    #[error(
        "the module exports no `kairos:policy/...@X.Y.Z#...` function of a released version (found: {0}); were its bindings generated from wit/since_vX.Y.Z?"
    )]
    UnknownVersion(String),
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
    let mut exports = Vec::new();
    for payload in wasmparser::Parser::new(0).parse_all(module) {
        let payload = payload.map_err(|e| ComponentizeError::NotWasm(e.to_string()))?;
        if let wasmparser::Payload::ExportSection(section) = &payload {
            for export in section.clone() {
                let export = export.map_err(|e| ComponentizeError::NotWasm(e.to_string()))?;
                exports.push(export.name.to_string());
            }
        }
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
    let source = wit_for_exports(&exports)?;
    let package = resolve.push_str("policy.wit", source).map_err(encode)?;
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

/// The embedded WIT whose version the module's `kairos:policy` exports name.
fn wit_for_exports(exports: &[String]) -> Result<&'static str, ComponentizeError> {
    let prefix = format!("{}/", super::inspect::PACKAGE);
    let named = exports.iter().find_map(|name| {
        let rest = name.strip_prefix(&prefix)?;
        let (_, version) = rest.split_once('@')?;
        let version = version.split('#').next()?;
        WIT_SOURCES
            .iter()
            .find(|(v, _)| v.to_string() == version)
            .map(|(_, source)| *source)
    });
    named.ok_or_else(|| {
        let found: Vec<&str> = exports
            .iter()
            .map(String::as_str)
            .filter(|n| !n.starts_with("cabi_") && !n.starts_with('_'))
            .take(8)
            .collect();
        ComponentizeError::UnknownVersion(if found.is_empty() {
            "nothing".into()
        } else {
            found.join(", ")
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_wit_version_comes_from_the_export_names() {
        let named =
            |names: &[&str]| -> Vec<String> { names.iter().map(|n| n.to_string()).collect() };
        let v1 = wit_for_exports(&named(&["memory", "kairos:policy/horizon@0.1.0#choose"]));
        assert!(v1.unwrap().contains("package kairos:policy@0.1.0;"));
        let v2 = wit_for_exports(&named(&[
            "kairos:policy/priority@0.2.0#rank",
            "cabi_realloc",
        ]));
        assert!(v2.unwrap().contains("package kairos:policy@0.2.0;"));
        let v3 = wit_for_exports(&named(&["kairos:policy/horizon@0.3.0#choose"]));
        assert!(v3.unwrap().contains("package kairos:policy@0.3.0;"));
        assert!(WIT_SOURCE.contains("package kairos:policy@0.3.0;"));
    }

    #[test]
    fn a_module_of_no_released_version_is_refused_naming_its_exports() {
        let err = wit_for_exports(&["kairos:policy/priority@9.9.9#rank".to_string()]).unwrap_err();
        assert!(err.to_string().contains("priority@9.9.9#rank"), "{err}");
        let module = wat::parse_str(r#"(module (func (export "choose")))"#).unwrap();
        let err = componentize(&module, PluginKind::Horizon).unwrap_err();
        assert!(matches!(err, ComponentizeError::UnknownVersion(_)), "{err}");
        assert!(err.to_string().contains("choose"), "{err}");
    }
}
