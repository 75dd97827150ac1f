//! Removal of what a killed process left behind in shared memory.

use iceoryx2::config::Config;
use iceoryx2::node::{NodeState, NodeView};
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
