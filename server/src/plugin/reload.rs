//! Hot reload: a thread per plugin file that notices a new version and compiles it.
//!
//! The thread polls the file's size and modification time. A change is acted on once the
//! file has stayed the same for one more poll (so a file being copied in place is not read
//! half-written); if its contents hash differs from the running version it is inspected and
//! compiled off the request path, and the result is handed to the wrapper, which swaps it in
//! between two calls. A new version that fails to load is logged and ignored: the running
//! version keeps serving.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::{Duration, SystemTime};

use sha2::{Digest, Sha256};

use super::PluginOptions;
use super::runtime::{Compiled, World, compile};

/// The receiving end of a plugin file's watcher. Dropping it stops the watcher.
pub(crate) struct Reloader<W: World> {
    updates: mpsc::Receiver<Arc<Compiled<W>>>,
    stop: Arc<AtomicBool>,
}

impl<W: World> Drop for Reloader<W> {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

impl<W: World> Reloader<W> {
    /// Watches `path`, currently loaded with contents hashing to `current`.
    pub fn spawn(
        path: PathBuf,
        current: [u8; 32],
        options: Arc<PluginOptions>,
        poll: Duration,
    ) -> std::io::Result<Self> {
        let (tx, updates) = mpsc::channel();
        let stop = Arc::new(AtomicBool::new(false));
        let stopped = stop.clone();
        let name = format!(
            "kairos-reload-{}",
            path.file_stem()
                .map(|s| s.to_string_lossy())
                .unwrap_or_default()
        );
        std::thread::Builder::new().name(name).spawn(move || {
            watch::<W>(&path, current, &options, poll, &stopped, &tx);
        })?;
        Ok(Reloader { updates, stop })
    }

    /// A newly compiled version, if one is ready.
    pub fn poll(&self) -> Option<Arc<Compiled<W>>> {
        let mut newest = None;
        while let Ok(plugin) = self.updates.try_recv() {
            newest = Some(plugin);
        }
        newest
    }
}

/// What identifies a version of the file without reading it: size, modification time and, on
/// Unix, the inode. The inode matters: file times are coarse (a few ms on Linux), so a new
/// version of the same size renamed into place right after the old one can carry the same
/// mtime, but never the same inode.
fn stat(path: &std::path::Path) -> Option<(u64, SystemTime, u64)> {
    let meta = std::fs::metadata(path).ok()?;
    #[cfg(unix)]
    let inode = std::os::unix::fs::MetadataExt::ino(&meta);
    #[cfg(not(unix))]
    let inode = 0;
    Some((meta.len(), meta.modified().ok()?, inode))
}

fn watch<W: World>(
    path: &std::path::Path,
    mut current: [u8; 32],
    options: &PluginOptions,
    poll: Duration,
    stop: &AtomicBool,
    tx: &mpsc::Sender<Arc<Compiled<W>>>,
) {
    let name = options.name.clone().unwrap_or_else(|| {
        path.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    });
    let mut seen = stat(path);
    // Not settled: the file is hashed once on the first quiet poll, because it may have been
    // replaced between the load and this thread's first `stat` (then `seen` already describes
    // the new version and no later change would ever be noticed).
    let mut settled = false;
    let mut rejected: Option<[u8; 32]> = None;
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(poll);
        let now = stat(path);
        if now != seen {
            seen = now;
            settled = false;
            continue;
        }
        if settled || now.is_none() {
            continue;
        }
        settled = true;
        let Ok(wasm) = std::fs::read(path) else {
            continue;
        };
        let hash: [u8; 32] = Sha256::digest(&wasm).into();
        if hash == current || Some(hash) == rejected {
            continue;
        }
        match compile::<W>(name.clone(), Some(path.to_path_buf()), &wasm, options) {
            Ok(plugin) => {
                tracing::info!(plugin = %name, sha256 = %hex::encode(&hash[..8]), "plugin file changed; new version compiled");
                current = hash;
                if tx.send(plugin).is_err() {
                    return;
                }
            }
            Err(error) => {
                tracing::error!(plugin = %name, %error, "plugin file changed but the new version cannot be loaded; keeping the running version");
                rejected = Some(hash);
            }
        }
    }
}
