//! Plugin components built in-test from WAT: well-behaved ones and hostile ones.
//!
//! Shared by the `plugin_*` modules of the server's integration test binary. Every fixture is a
//! real component: a core module assembled from WAT with `wat`, given the `kairos:policy`
//! world and encoded with `wit-component` (through the server's own componentize step, or
//! directly for worlds the server does not know).

#![allow(dead_code)]

use std::path::PathBuf;
use std::time::Duration;

use kairos_core::horizon::{HorizonError, HorizonInput, HorizonPolicy};
use kairos_core::scheduler::{PendingView, PolicyError, PriorityPolicy};
use kairos_core::time::Timestamp;
use kairos_server::plugin::PluginKind;
use kairos_server::plugin::cache::CodeCache;
use kairos_server::plugin::componentize::componentize;
use kairos_server::plugin::{PluginOptions, PluginSource, WasmHorizonPolicy};

/// The repository root.
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A shipped plugin built by `plugins/build.sh` (`plugins/build/NAME.wasm`); a missing one fails
/// the test with how to build it.
pub fn shipped_plugin(name: &str) -> PathBuf {
    let path = repo_root()
        .join("plugins/build")
        .join(format!("{name}.wasm"));
    assert!(
        path.exists(),
        "{} is missing: build the shipped plugins first with \
         `bash scripts/install-plugin-toolchains.sh && bash plugins/build.sh` (CI's .ci/run does)",
        path.display()
    );
    path
}

/// A bump allocator for the canonical ABI; `post-return` resets it, so a reused instance
/// does not grow. Addresses 0..64 are the return area.
const ALLOCATOR: &str = r#"
  (memory (export "memory") 1)
  (global $heap (mut i32) (i32.const 1024))
  (func $alloc (export "cabi_realloc") (param i32 i32 i32 i32) (result i32)
    (local $p i32)
    (local.set $p
      (i32.and
        (i32.add (global.get $heap) (i32.sub (local.get 2) (i32.const 1)))
        (i32.xor (i32.sub (local.get 2) (i32.const 1)) (i32.const -1))))
    (global.set $heap (i32.add (local.get $p) (local.get 3)))
    (block $fits
      (br_if $fits (i32.le_u (global.get $heap) (i32.mul (memory.size) (i32.const 65536))))
      (br_if $fits
        (i32.ne (i32.const -1)
          (memory.grow
            (i32.add (i32.const 1)
              (i32.div_u
                (i32.sub (global.get $heap) (i32.mul (memory.size) (i32.const 65536)))
                (i32.const 65536))))))
      unreachable)
    (local.get $p))
"#;

/// A horizon core module whose `choose` runs `body` (locals: 0-3 S K N D, 4-7 the two lists,
/// 8 h_min, 9 h_max, 10 control_hz, 11 round_index, 12-13 recent, 14-15 params) and answers
/// `ok(<i32 left on the stack>)`.
pub fn horizon_wat(body: &str) -> String {
    format!(
        r#"(module
  {ALLOCATOR}
  (func (export "kairos:policy/horizon@0.1.0#choose")
    (param i32 i32 i32 i32 i32 i32 i32 i32 i32 i32 f32 i64 i32 i32 i32 i32) (result i32)
    (local $h i32)
    {body}
    (local.set $h)
    (i32.store8 (i32.const 0) (i32.const 0))
    (i32.store (i32.const 4) (local.get $h))
    (i32.const 0))
  (func (export "cabi_post_kairos:policy/horizon@0.1.0#choose") (param i32)
    (global.set $heap (i32.const 1024)))
)"#
    )
}

/// A priority core module whose `order` runs `body` with the pending list at locals 1-2
/// (ptr, len); `body` must leave (ptr, len) of the answer list on the stack.
pub fn priority_wat(body: &str) -> String {
    priority_wat_notified(body, "")
}

/// [`priority_wat`] whose `task-finished` runs `finished` (locals 0-4: task, rounds, latency,
/// attained service, wait; it leaves nothing on the stack).
pub fn priority_wat_notified(body: &str, finished: &str) -> String {
    format!(
        r#"(module
  {ALLOCATOR}
  (func (export "kairos:policy/priority@0.1.0#order")
    (param i64 i32 i32 i32 i32) (result i32)
    (local $i i32) (local $out i32) (local $len i32)
    {body}
    (local.set $len)
    (local.set $out)
    (i32.store8 (i32.const 0) (i32.const 0))
    (i32.store (i32.const 4) (local.get $out))
    (i32.store (i32.const 8) (local.get $len))
    (i32.const 0))
  (func (export "cabi_post_kairos:policy/priority@0.1.0#order") (param i32)
    (global.set $heap (i32.const 1024)))
  (func (export "kairos:policy/priority@0.1.0#task-finished")
    (param i64 i32 i64 i64 i64)
    {finished})
)"#
    )
}

/// `ok(h_min)`: a correct (if timid) horizon policy.
pub const HORIZON_H_MIN: &str = "(local.get 8)";
/// `ok(h_max)`.
pub const HORIZON_H_MAX: &str = "(local.get 9)";
/// Loops forever.
pub const HORIZON_LOOP: &str = "(loop $spin (br $spin)) (i32.const 1)";
/// Grows memory by 1 MiB at a time, forever.
pub const HORIZON_HOG: &str =
    "(loop $grow (drop (memory.grow (i32.const 16))) (br $grow)) (i32.const 1)";
/// Traps.
pub const HORIZON_TRAP: &str = "unreachable";
/// Answers one more than `h_max`.
pub const HORIZON_TOO_LONG: &str = "(i32.add (local.get 9) (i32.const 1))";
/// Answers 0.
pub const HORIZON_ZERO: &str = "(i32.const 0)";

/// The identity order `[0, 1, ..., len-1]`: arrival-list order.
pub const PRIORITY_IDENTITY: &str = r#"
    (local.set $out (call $alloc (i32.const 0) (i32.const 0) (i32.const 4) (i32.shl (local.get 2) (i32.const 2))))
    (local.set $i (i32.const 0))
    (block $done
      (loop $fill
        (br_if $done (i32.ge_u (local.get $i) (local.get 2)))
        (i32.store (i32.add (local.get $out) (i32.shl (local.get $i) (i32.const 2))) (local.get $i))
        (local.set $i (i32.add (local.get $i) (i32.const 1)))
        (br $fill)))
    (local.get $out) (local.get 2)"#;
/// Omits the last request.
pub const PRIORITY_OMIT: &str = r#"
    (local.set $out (call $alloc (i32.const 0) (i32.const 0) (i32.const 4) (i32.shl (local.get 2) (i32.const 2))))
    (local.set $i (i32.const 0))
    (block $done
      (loop $fill
        (br_if $done (i32.ge_u (local.get $i) (local.get 2)))
        (i32.store (i32.add (local.get $out) (i32.shl (local.get $i) (i32.const 2))) (local.get $i))
        (local.set $i (i32.add (local.get $i) (i32.const 1)))
        (br $fill)))
    (local.get $out)
    (select (i32.sub (local.get 2) (i32.const 1)) (i32.const 0) (local.get 2))"#;
/// Lists request 0 `len` times.
pub const PRIORITY_DUPLICATE: &str = r#"
    (local.set $out (call $alloc (i32.const 0) (i32.const 0) (i32.const 4) (i32.shl (local.get 2) (i32.const 2))))
    (memory.fill (local.get $out) (i32.const 0) (i32.shl (local.get 2) (i32.const 2)))
    (local.get $out) (local.get 2)"#;
/// Loops forever (a `task-finished` body).
pub const FINISHED_LOOP: &str = "(loop $spin (br $spin))";
/// Loops forever.
pub const PRIORITY_LOOP: &str = "(loop $spin (br $spin)) (i32.const 0) (i32.const 0)";
/// Grows memory forever.
pub const PRIORITY_HOG: &str =
    "(loop $grow (drop (memory.grow (i32.const 16))) (br $grow)) (i32.const 0) (i32.const 0)";
/// Traps.
pub const PRIORITY_TRAP: &str = "unreachable";

/// A component of `kind` from a WAT core module.
pub fn component(wat: &str, kind: PluginKind) -> Vec<u8> {
    let module = wat::parse_str(wat).expect("fixture WAT assembles");
    componentize(&module, kind).expect("fixture componentizes")
}

/// A horizon component whose `choose` runs `body`.
pub fn horizon_component(body: &str) -> Vec<u8> {
    component(&horizon_wat(body), PluginKind::Horizon)
}

/// A priority component whose `order` runs `body`.
pub fn priority_component(body: &str) -> Vec<u8> {
    component(&priority_wat(body), PluginKind::Priority)
}

/// A component for a WIT the server does not embed: `wit` is the whole package source,
/// `world` the world to target, `wat` the core module.
pub fn foreign_component(wit: &str, world: &str, wat: &str) -> Vec<u8> {
    let mut resolve = wit_parser::Resolve::default();
    let package = resolve
        .push_str("foreign.wit", wit)
        .expect("fixture WIT parses");
    let world = resolve
        .select_world(&[package], Some(world))
        .expect("fixture world exists");
    let mut module = wat::parse_str(wat).expect("fixture WAT assembles");
    wit_component::embed_component_metadata(
        &mut module,
        &resolve,
        world,
        wit_component::StringEncoding::UTF8,
    )
    .expect("metadata embeds");
    wit_component::ComponentEncoder::default()
        .validate(true)
        .module(&module)
        .expect("module accepted")
        .encode()
        .expect("component encodes")
}

/// The released WIT with its version replaced, for "built against a newer server" fixtures.
pub fn wit_with_version(version: &str) -> String {
    // The fixtures' WAT exports 0.1.0's functions, so the base is 0.1.0's WIT.
    kairos_server::plugin::componentize::WIT_SOURCES[0]
        .1
        .replace("kairos:policy@0.1.0", &format!("kairos:policy@{version}"))
}

// Equality tests of shipped plugins against their native twins (plugin_twins, load_horizon).

/// Plugin options for equality tests.
pub fn options(base: PluginOptions) -> PluginOptions {
    let cache = repo_root().join("plugins/build/cache");
    PluginOptions {
        // Equality, not speed, is under test: generous limits so a loaded machine cannot
        // turn a slow call into a fallback answer.
        deadline: Duration::from_secs(5),
        memory_limit: 256 << 20,
        reload_poll: None,
        cache: Some(CodeCache::open(cache).expect("plugin cache")),
        ..base
    }
}

/// A horizon policy that must never be asked: equality tests compare the plugin itself.
pub struct Unreachable;

impl HorizonPolicy for Unreachable {
    fn name(&self) -> &str {
        "unreachable"
    }
    fn choose(&mut self, _: &HorizonInput<'_>) -> Result<usize, HorizonError> {
        panic!("the fallback answered: the plugin failed")
    }
}

impl PriorityPolicy for Unreachable {
    fn name(&self) -> &str {
        "unreachable"
    }
    fn order(
        &mut self,
        _: Timestamp,
        _: &[PendingView],
        _: &mut Vec<usize>,
    ) -> Result<(), PolicyError> {
        panic!("the fallback answered: the plugin failed")
    }
}

/// Loads the shipped horizon plugin `name`, with a fallback that must never answer.
pub fn horizon_plugin(name: &str) -> WasmHorizonPolicy {
    WasmHorizonPolicy::load(
        &PluginSource::File(shipped_plugin(name)),
        options(PluginOptions::horizon()),
        Box::new(Unreachable),
    )
    .unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// Errors agree when they are the same kind about the same parameter; messages are prose.
pub fn same_answer(
    native: &Result<usize, HorizonError>,
    plugin: &Result<usize, HorizonError>,
) -> bool {
    match (native, plugin) {
        (Ok(a), Ok(b)) => a == b,
        (
            Err(HorizonError::InvalidParam { name: a, .. }),
            Err(HorizonError::InvalidParam { name: b, .. }),
        ) => a == b,
        (Err(HorizonError::Unsupported(_)), Err(HorizonError::Unsupported(_))) => true,
        _ => false,
    }
}
