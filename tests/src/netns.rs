//! A Linux network namespace joined to the test's own by a veth pair: a second network stack for
//! tests that need traffic to cross a real interface (a "far" worker behind the delay relay of
//! [`crate::proxy`]). Needs root and `ip` (iproute2); `scripts/test.sh` installs iproute2 when it
//! is missing, and a test that cannot create the namespace fails with [`NetNsError`]'s message
//! rather than skipping.
//!
//! Names and addresses are unique per process and namespace (the pid and a counter), so parallel
//! test runs do not collide: namespace `kairos-<pid>-<n>`, host interface `kv<pid>x<n>`, peer
//! `kv<pid>y<n>`, and a /30 of 10.0.0.0/8 picked from the pid and counter (host `.1`, namespace
//! `.2`). [`NetNs`] deletes both on drop, also when the test panics.

use std::fs::File;
use std::net::Ipv4Addr;
use std::os::fd::AsRawFd;
use std::process::Command;
use std::sync::atomic::{AtomicU32, Ordering};
use std::thread::JoinHandle;

/// Namespaces this process created so far (part of the names and the subnet).
static CREATED: AtomicU32 = AtomicU32::new(0);

/// Why a namespace could not be created or entered.
#[derive(Debug, thiserror::Error)]
pub enum NetNsError {
    /// `ip` could not be run at all.
    #[error("cannot run `ip {args}` (install iproute2): {source}")]
    Spawn {
        /// The arguments.
        args: String,
        /// Why.
        source: std::io::Error,
    },
    /// `ip` failed (not root, no netns support, a name taken).
    #[error("`ip {args}` failed (network namespaces need root): {stderr}")]
    Failed {
        /// The arguments.
        args: String,
        /// What `ip` said.
        stderr: String,
    },
    /// The thread could not join the namespace.
    #[error("cannot enter network namespace {name}: {source}")]
    Enter {
        /// The namespace.
        name: String,
        /// Why.
        source: std::io::Error,
    },
}

/// A network namespace with one veth pair to the creating one; deleted on drop.
#[derive(Debug)]
pub struct NetNs {
    name: String,
    host_if: String,
    /// The host side's address (in the test's namespace), reachable from inside.
    pub host_ip: Ipv4Addr,
    /// The namespace side's address.
    pub ns_ip: Ipv4Addr,
}

fn ip(args: &[&str]) -> Result<(), NetNsError> {
    let joined = args.join(" ");
    let out = Command::new("ip")
        .args(args)
        .output()
        .map_err(|source| NetNsError::Spawn {
            args: joined.clone(),
            source,
        })?;
    if out.status.success() {
        Ok(())
    } else {
        Err(NetNsError::Failed {
            args: joined,
            stderr: String::from_utf8_lossy(&out.stderr).trim().to_owned(),
        })
    }
}

impl NetNs {
    /// Creates the namespace, the veth pair, their addresses, and brings the links up.
    pub fn create() -> Result<NetNs, NetNsError> {
        let pid = std::process::id();
        let n = CREATED.fetch_add(1, Ordering::Relaxed);
        // One /30 per (pid, n): 2^22 of them in 10.0.0.0/8.
        let index = (pid.wrapping_mul(8).wrapping_add(n)) % (1 << 22);
        let base = u32::from(Ipv4Addr::new(10, 0, 0, 0)) + index * 4;
        let netns = NetNs {
            name: format!("kairos-{pid}-{n}"),
            host_if: format!("kv{pid}x{n}"),
            host_ip: Ipv4Addr::from(base + 1),
            ns_ip: Ipv4Addr::from(base + 2),
        };
        // From here on, drop cleans up whatever part was made.
        let peer = format!("kv{pid}y{n}");
        let (name, host_if) = (netns.name.as_str(), netns.host_if.as_str());
        let host_cidr = format!("{}/30", netns.host_ip);
        let ns_cidr = format!("{}/30", netns.ns_ip);
        // A namespace left by an earlier process with the same pid (killed before its drop).
        let _ = ip(&["link", "del", host_if]);
        let _ = ip(&["netns", "del", name]);
        ip(&["netns", "add", name])?;
        ip(&[
            "link", "add", host_if, "type", "veth", "peer", "name", &peer, "netns", name,
        ])?;
        ip(&["addr", "add", &host_cidr, "dev", host_if])?;
        ip(&["link", "set", host_if, "up"])?;
        ip(&["-n", name, "addr", "add", &ns_cidr, "dev", &peer])?;
        ip(&["-n", name, "link", "set", &peer, "up"])?;
        ip(&["-n", name, "link", "set", "lo", "up"])?;
        Ok(netns)
    }

    /// The namespace's name (`ip netns exec <name> …`).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Runs `f` on a new OS thread that first joins the namespace: every socket it (or a
    /// runtime it builds) creates lives there. The thread returns [`NetNsError::Enter`] instead
    /// of running `f` in the wrong namespace.
    pub fn spawn<R: Send + 'static>(
        &self,
        f: impl FnOnce() -> R + Send + 'static,
    ) -> JoinHandle<Result<R, NetNsError>> {
        let name = self.name.clone();
        std::thread::spawn(move || {
            let enter = |source| NetNsError::Enter {
                name: name.clone(),
                source,
            };
            let handle = File::open(format!("/run/netns/{name}")).map_err(enter)?;
            // SAFETY: `setns` only reads the descriptor, which `handle` keeps open for the call,
            // and changes the network namespace of this thread alone (CLONE_NEWNET is allowed
            // in a multi-threaded process); no memory is shared with the kernel.
            let joined = unsafe { libc::setns(handle.as_raw_fd(), libc::CLONE_NEWNET) };
            if joined != 0 {
                return Err(enter(std::io::Error::last_os_error()));
            }
            Ok(f())
        })
    }
}

impl Drop for NetNs {
    fn drop(&mut self) {
        // Deleting the host side removes its peer; deleting the namespace removes the rest.
        if let Err(error) = ip(&["link", "del", &self.host_if]) {
            eprintln!("netns cleanup: {error}");
        }
        if let Err(error) = ip(&["netns", "del", &self.name]) {
            eprintln!("netns cleanup: {error}");
        }
    }
}
