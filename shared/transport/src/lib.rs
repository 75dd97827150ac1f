//! Typed, zero-copy transport between PoseFlow stages over iceoryx2.
//!
//! An **edge** of a graph is a pair of iceoryx2 services with the same name:
//! publish-subscribe carrying `[f32]` payloads with a contract header as the
//! user header, and an event service whose notifications wake the receivers
//! (so nobody polls or sleeps). Service names are
//! `poseflow/<graph instance>/<edge>`, so graphs with different instance
//! names never see each other's traffic.

mod blocked;
mod cleanup;
mod error;
mod naming;
mod pubsub;
mod request;
mod untyped;

pub use cleanup::{remove_dead_nodes, shared_memory_files};
pub use error::TransportError;
pub use naming::{edge_service_name, heartbeat_service_name, validate_name};
pub use pubsub::{EdgeOptions, EdgeSubscriber, EndOfStream, Overflow, Publisher, Received, events};
pub use request::{Reply, RequestClient, RequestServer, Responder};
pub use untyped::{UntypedPublisher, UntypedSubscriber, untyped_publisher, untyped_subscriber};

/// The iceoryx2 service variant used across the project: inter-process.
pub type Ipc = iceoryx2::service::ipc::Service;
/// A node of this process.
pub type Node = iceoryx2::node::Node<Ipc>;

/// Whether SIGINT/SIGTERM arrived, without hiding it from the stage's own
/// loop: iceoryx2 clears the flag when it is read, so it is raised again.
pub fn termination_requested() -> bool {
    let requested = iceoryx2_bb_posix::signal::SignalHandler::termination_requested();
    if requested {
        // SAFETY: raise() only re-delivers SIGTERM to this thread, where
        // iceoryx2's handler records it again.
        unsafe { libc::raise(libc::SIGTERM) };
    }
    requested
}

/// Creates this process's iceoryx2 node, named after the stage.
///
/// Signal handling is left to iceoryx2's default: SIGINT/SIGTERM end the
/// WaitSet loops, and the stage then drops its ports and node, which removes
/// their shared memory.
pub fn create_node(name: &str) -> Result<Node, TransportError> {
    let node_name =
        name.try_into().map_err(|e| TransportError::Name { name: name.to_string(), detail: format!("{e:?}") })?;
    iceoryx2::node::NodeBuilder::new()
        .name(&node_name)
        .create::<Ipc>()
        .map_err(|e| TransportError::iceoryx("create node", name, e))
}
