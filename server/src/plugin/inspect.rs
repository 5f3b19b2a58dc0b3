//! What a component is, read from its bytes before anything is compiled or run.
//!
//! The world a component targets and its version are read from the names of its exports
//! (`kairos:policy/horizon@0.1.0`), and its imports are checked against what the host grants:
//! nothing for a plain component, deny-all WASI for one built by a toolchain that links a
//! language runtime (componentize-py). Anything else is refused here with a message that names
//! the offending export or import.

use wit_parser::{Resolve, WorldItem, WorldKey};

use super::PluginKind;
use super::bindings::WitVersion;

/// The WIT package plugins implement.
pub const PACKAGE: &str = "kairos:policy";

/// WIT package versions this server can load, oldest first. A component built against any of
/// them is called through the bindings of that version (see `bindings`).
pub const SUPPORTED: &[WitVersion] = &[
    super::bindings::since_v0_1_0::VERSION,
    super::bindings::since_v0_2_0::VERSION,
    super::bindings::since_v0_3_0::VERSION,
];

/// What a component says about itself.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ComponentInfo {
    /// Policy interfaces it exports, with the package version of each.
    pub exports: Vec<(PluginKind, WitVersion)>,
    /// Every interface or function it imports, as fully qualified names.
    pub imports: Vec<String>,
    /// Whether it imports WASI (then it runs with a WASI context that grants nothing).
    pub imports_wasi: bool,
}

/// Why a file is not a usable plugin of the requested kind.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum InspectError {
    /// Not a WebAssembly component (a core module, or not WebAssembly at all).
    #[error(
        "not a WebAssembly component: {0} (a C core module must be turned into a component first: `kairos plugin componentize`)"
    )]
    NotAComponent(String),
    /// It exports neither policy interface of `kairos:policy`.
    #[error(
        "exports no `kairos:policy` interface (found: {found}); a plugin must target world `horizon-policy` or `priority-policy`"
    )]
    NoPolicyExport {
        /// What it exports instead.
        found: String,
    },
    /// It implements the other world.
    #[error(
        "is a {found} plugin (it exports `{PACKAGE}/{found}`), but was loaded as a {expected} plugin"
    )]
    WrongWorld {
        /// What the caller asked for.
        expected: PluginKind,
        /// What the component implements.
        found: PluginKind,
    },
    /// It targets a version of the interfaces this server does not support.
    #[error(
        "targets {PACKAGE}@{found}, which this server does not support (supported: {supported})"
    )]
    UnsupportedVersion {
        /// Its version.
        found: WitVersion,
        /// What this server supports.
        supported: String,
    },
    /// It imports something the sandbox does not provide.
    #[error(
        "imports `{0}`, which the sandbox does not provide (plugins may import nothing, or WASI 0.2, which grants no capabilities)"
    )]
    ForbiddenImport(String),
}

impl ComponentInfo {
    /// The version of the `kind` interface this component exports, if it is usable as one.
    pub fn check(&self, kind: PluginKind) -> Result<WitVersion, InspectError> {
        let Some(&(_, version)) = self.exports.iter().find(|(k, _)| *k == kind) else {
            return Err(match self.exports.first() {
                Some(&(found, _)) => InspectError::WrongWorld {
                    expected: kind,
                    found,
                },
                None => InspectError::NoPolicyExport {
                    found: "nothing".into(),
                },
            });
        };
        if !SUPPORTED.contains(&version) {
            return Err(InspectError::UnsupportedVersion {
                found: version,
                supported: SUPPORTED
                    .iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
        Ok(version)
    }
}

/// Reads the world of the component in `wasm`.
pub fn inspect(wasm: &[u8]) -> Result<ComponentInfo, InspectError> {
    if wasmparser::Parser::is_core_wasm(wasm) {
        return Err(InspectError::NotAComponent("this is a core module".into()));
    }
    let decoded = wit_parser::decoding::decode(wasm)
        .map_err(|e| InspectError::NotAComponent(format!("{e:#}")))?;
    let wit_parser::decoding::DecodedWasm::Component(resolve, world) = decoded else {
        return Err(InspectError::NotAComponent(
            "this is a WIT package, not a component".into(),
        ));
    };
    let world = &resolve.worlds[world];

    let mut exports = Vec::new();
    let mut other_exports = Vec::new();
    for (key, item) in &world.exports {
        match policy_interface(&resolve, key, item) {
            Some(export) => exports.push(export),
            None => other_exports.push(resolve.name_world_key(key)),
        }
    }
    if exports.is_empty() {
        return Err(InspectError::NoPolicyExport {
            found: if other_exports.is_empty() {
                "nothing".into()
            } else {
                other_exports.join(", ")
            },
        });
    }

    let mut imports = Vec::new();
    let mut imports_wasi = false;
    for (key, item) in &world.imports {
        let name = resolve.name_world_key(key);
        match import_class(&resolve, key, item) {
            ImportClass::TypesOnly => {}
            ImportClass::Wasi => imports_wasi = true,
            ImportClass::Other => return Err(InspectError::ForbiddenImport(name)),
        }
        imports.push(name);
    }
    Ok(ComponentInfo {
        exports,
        imports,
        imports_wasi,
    })
}

fn policy_interface(
    resolve: &Resolve,
    key: &WorldKey,
    item: &WorldItem,
) -> Option<(PluginKind, WitVersion)> {
    let (WorldKey::Interface(id), WorldItem::Interface { .. }) = (key, item) else {
        return None;
    };
    let interface = &resolve.interfaces[*id];
    let package = &resolve.packages[interface.package?].name;
    if package.namespace != "kairos" || package.name != "policy" {
        return None;
    }
    let kind = match interface.name.as_deref()? {
        "horizon" => PluginKind::Horizon,
        "priority" => PluginKind::Priority,
        _ => return None,
    };
    let version = package.version.as_ref()?;
    if !version.pre.is_empty() {
        return None;
    }
    Some((
        kind,
        WitVersion::new(version.major, version.minor, version.patch),
    ))
}

enum ImportClass {
    /// An interface with types and no functions (e.g. `kairos:policy/types`): nothing to run.
    TypesOnly,
    /// A WASI 0.2 interface: linked to a context that grants nothing.
    Wasi,
    /// Anything else: refused.
    Other,
}

fn import_class(resolve: &Resolve, key: &WorldKey, item: &WorldItem) -> ImportClass {
    match (key, item) {
        (WorldKey::Interface(id), WorldItem::Interface { .. }) => {
            let interface = &resolve.interfaces[*id];
            let package = interface.package.map(|p| &resolve.packages[p].name);
            if let Some(package) = package {
                if package.namespace == "wasi"
                    && package
                        .version
                        .as_ref()
                        .is_some_and(|v| v.major == 0 && v.minor == 2)
                {
                    return ImportClass::Wasi;
                }
                if package.namespace == "kairos"
                    && package.name == "policy"
                    && interface.functions.is_empty()
                {
                    return ImportClass::TypesOnly;
                }
            }
            ImportClass::Other
        }
        (_, WorldItem::Type { .. }) => ImportClass::TypesOnly,
        _ => ImportClass::Other,
    }
}
