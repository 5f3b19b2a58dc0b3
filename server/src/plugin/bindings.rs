//! Host bindings, one module per frozen WIT directory in `wit/`.
//!
//! Each `since_vX_Y_Z` module is generated from `wit/since_vX.Y.Z/` and never edited by hand.
//! A plugin built against any version listed in [`SUPPORTED`] is loaded through the module of
//! that version; the wrappers convert the server's types into that version's types.

/// Bindings for `kairos:policy@0.1.0` (`wit/since_v0.1.0/`).
pub mod since_v0_1_0 {
    /// The WIT package version these bindings were generated from.
    pub const VERSION: super::WitVersion = super::WitVersion::new(0, 1, 0);

    /// The `horizon-policy` world. Borrowing bindings: the chunk's buffers are lowered
    /// straight from the caller's slices, with no intermediate copy.
    #[allow(missing_docs)]
    pub mod horizon {
        wasmtime::component::bindgen!({
            path: "../wit/since_v0.1.0",
            world: "horizon-policy",
            ownership: Borrowing { duplicate_if_necessary: false },
        });
    }

    /// The `priority-policy` world.
    #[allow(missing_docs)]
    pub mod priority {
        wasmtime::component::bindgen!({
            path: "../wit/since_v0.1.0",
            world: "priority-policy",
        });
    }
}

/// Bindings for `kairos:policy@0.2.0` (`wit/since_v0.2.0/`).
pub mod since_v0_2_0 {
    /// The WIT package version these bindings were generated from.
    pub const VERSION: super::WitVersion = super::WitVersion::new(0, 2, 0);

    /// The `horizon-policy` world (unchanged since 0.1.0 but for the package version).
    #[allow(missing_docs)]
    pub mod horizon {
        wasmtime::component::bindgen!({
            path: "../wit/since_v0.2.0",
            world: "horizon-policy",
            ownership: Borrowing { duplicate_if_necessary: false },
        });
    }

    /// The `priority-policy` world. Owning bindings (borrowing ones do not compile for this
    /// world in wasmtime 48); arguments are still lowered by reference, so the host keeps one
    /// `PendingColumns` and refills its vectors: each column is one block copy per call.
    #[allow(missing_docs)]
    pub mod priority {
        wasmtime::component::bindgen!({
            path: "../wit/since_v0.2.0",
            world: "priority-policy",
        });
    }
}

/// Bindings for `kairos:policy@0.3.0` (`wit/since_v0.3.0/`).
pub mod since_v0_3_0 {
    /// The WIT package version these bindings were generated from.
    pub const VERSION: super::WitVersion = super::WitVersion::new(0, 3, 0);

    /// The `horizon-policy` world: 0.2.0's, with the server's load in the context.
    #[allow(missing_docs)]
    pub mod horizon {
        wasmtime::component::bindgen!({
            path: "../wit/since_v0.3.0",
            world: "horizon-policy",
            ownership: Borrowing { duplicate_if_necessary: false },
        });
    }

    /// The `priority-policy` world (unchanged since 0.2.0 but for the package version).
    #[allow(missing_docs)]
    pub mod priority {
        wasmtime::component::bindgen!({
            path: "../wit/since_v0.3.0",
            world: "priority-policy",
        });
    }
}

/// A WIT package version, `major.minor.patch`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct WitVersion {
    /// Major.
    pub major: u64,
    /// Minor.
    pub minor: u64,
    /// Patch.
    pub patch: u64,
}

impl WitVersion {
    /// `major.minor.patch`.
    pub const fn new(major: u64, minor: u64, patch: u64) -> Self {
        WitVersion {
            major,
            minor,
            patch,
        }
    }
}

impl std::fmt::Display for WitVersion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}.{}.{}", self.major, self.minor, self.patch)
    }
}
