//! Removal of what a killed process left behind in shared memory.

use iceoryx2::config::Config;
use iceoryx2::node::{NodeCleanupFailure, NodeState, NodeView};
use iceoryx2::prelude::CallbackProgression;

use crate::{Ipc, TransportError};

/// Finds nodes whose process died without cleaning up (SIGKILL, crash) and
/// removes their stale resources. Returns how many were removed.
pub fn remove_dead_nodes() -> Result<usize, TransportError> {
    let mut removed = 0;
    let mut failure = None;
    iceoryx2::node::Node::<Ipc>::list(Config::global_config(), |state| {
        if let NodeState::Dead(dead) = state {
            let name = dead.details().as_ref().map(|d| d.name().to_string()).unwrap_or_default();
            match dead.try_remove_stale_resources() {
                Ok(_) => {
                    tracing::info!(node = %name, "removed stale resources of a dead node");
                    removed += 1;
                }
                // Graphs starting side by side race for the same dead node:
                // the other one removing it is what this call wanted.
                Err(NodeCleanupFailure::AnotherInstanceIsCleaningUpTheNode)
                | Err(NodeCleanupFailure::ResourcesAlreadyCleanedUp) => {
                    tracing::debug!(node = %name, "stale resources removed by another process")
                }
                Err(e) => failure = Some(TransportError::iceoryx("remove stale resources of", &name, e)),
            }
        }
        CallbackProgression::Continue
    })
    .map_err(|e| TransportError::iceoryx("list", "nodes", e))?;
    match failure {
        Some(err) => Err(err),
        None => Ok(removed),
    }
}

/// Every file iceoryx2 keeps in shared memory (`/dev/shm/iox2_*`) or under
/// `/tmp/iceoryx2` (the roots `config/iceoryx2.toml` leaves at their
/// defaults): compare two snapshots to find what a run leaked.
pub fn shared_memory_files() -> std::collections::BTreeSet<std::path::PathBuf> {
    fn walk(dir: &std::path::Path, out: &mut std::collections::BTreeSet<std::path::PathBuf>) {
        for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let path = entry.path();
            if path.is_dir() {
                walk(&path, out);
            } else {
                out.insert(path);
            }
        }
    }
    let mut files = std::collections::BTreeSet::new();
    walk(std::path::Path::new("/tmp/iceoryx2"), &mut files);
    for entry in std::fs::read_dir("/dev/shm").into_iter().flatten().flatten() {
        if entry.file_name().to_string_lossy().starts_with("iox2_") {
            files.insert(entry.path());
        }
    }
    files
}
