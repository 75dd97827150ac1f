//! Publish-subscribe of contract messages (`H` user header + `[f32]`
//! payload), with event notifications for wake-up.

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher as IoxPublisher;
use iceoryx2::port::subscriber::Subscriber as IoxSubscriber;
use iceoryx2::prelude::{
    AllocationStrategy, BackpressureStrategy, FileDescriptor, FileDescriptorBased,
    SynchronousMultiplexing,
};
use iceoryx2::sample::Sample;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;
use poseflow_contracts::MessageHeader;

use crate::{Ipc, Node, TransportError};

/// Event ids on an edge's event service.
pub mod events {
    use iceoryx2::port::event_id::EventId;

    /// A new sample was published.
    pub const DATA: EventId = EventId::new(0);
    /// The publisher has sent its last sample; receivers drain and finish.
    pub const END_OF_STREAM: EventId = EventId::new(1);
    /// Highest id in use (sizes the event service).
    pub const MAX: usize = 1;
}

/// What a full receive queue does to a new sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Overflow {
    /// The oldest queued sample is replaced (fresh data wins; tracking).
    DropOldest,
    /// The publisher waits until the receiver has room (nothing is lost).
    Block,
}

/// Settings of one edge. Every participant of an edge must use the same
/// `queue` and `overflow` (iceoryx2 checks them when a port opens the
/// service); the graph file is the single source of both.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EdgeOptions {
    pub queue: usize,
    pub overflow: Overflow,
    /// Payload capacity reserved up front, in `f32` values; larger payloads
    /// reallocate (power-of-two growth).
    pub initial_payload_len: usize,
}

impl Default for EdgeOptions {
    fn default() -> Self {
        Self {
            queue: 4,
            overflow: Overflow::DropOldest,
            initial_payload_len: 4096,
        }
    }
}

/// Ports of a restarted process coexist briefly with its dead predecessor's
/// until stale resources are removed, so capacities leave room for that.
const MAX_PUBLISHERS: usize = 4;
const MAX_SUBSCRIBERS: usize = 16;
const MAX_NODES: usize = 32;

fn open_pubsub<H: MessageHeader>(
    node: &Node,
    name: &str,
    options: &EdgeOptions,
) -> Result<PortFactory<Ipc, [f32], H>, TransportError> {
    let service_name = name.try_into().map_err(|e| TransportError::Name {
        name: name.to_string(),
        detail: format!("{e:?}"),
    })?;
    node.service_builder(&service_name)
        .publish_subscribe::<[f32]>()
        .user_header::<H>()
        .subscriber_max_buffer_size(options.queue)
        .history_size(0)
        .enable_safe_overflow(options.overflow == Overflow::DropOldest)
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(|e| TransportError::iceoryx("open publish-subscribe service", name, e))
}

fn open_event(
    node: &Node,
    name: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<Ipc>, TransportError> {
    let service_name = name.try_into().map_err(|e| TransportError::Name {
        name: name.to_string(),
        detail: format!("{e:?}"),
    })?;
    node.service_builder(&service_name)
        .event()
        .max_notifiers(MAX_PUBLISHERS)
        .max_listeners(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .event_id_max_value(events::MAX)
        .open_or_create()
        .map_err(|e| TransportError::iceoryx("open event service", name, e))
}

/// The event service on which receivers acknowledge end-of-stream.
fn ack_name(edge: &str) -> String {
    format!("{edge}/ack")
}

/// How an end-of-stream handshake ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EndOfStream {
    /// Receivers connected when the stream ended.
    pub receivers: usize,
    /// Receivers that acknowledged having drained the edge in time.
    pub acknowledged: usize,
}

/// The sending end of an edge.
#[derive(Debug)]
pub struct Publisher<H: MessageHeader> {
    name: String,
    service: PortFactory<Ipc, [f32], H>,
    publisher: IoxPublisher<Ipc, [f32], H>,
    notifier: Notifier<Ipc>,
    acks: Listener<Ipc>,
}

impl<H: MessageHeader> Publisher<H> {
    pub fn create(node: &Node, name: &str, options: &EdgeOptions) -> Result<Self, TransportError> {
        let service = open_pubsub::<H>(node, name, options)?;
        let backpressure = match options.overflow {
            Overflow::DropOldest => BackpressureStrategy::DiscardData,
            Overflow::Block => BackpressureStrategy::RetryUntilDelivered,
        };
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(options.initial_payload_len.max(1))
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(backpressure)
            .create()
            .map_err(|e| TransportError::iceoryx("create publisher on", name, e))?;
        let notifier = open_event(node, name)?
            .notifier_builder()
            .create()
            .map_err(|e| TransportError::iceoryx("create notifier on", name, e))?;
        let acks = open_event(node, &ack_name(name))?
            .listener_builder()
            .create()
            .map_err(|e| TransportError::iceoryx("create listener on", name, e))?;
        Ok(Self {
            name: name.to_string(),
            service,
            publisher,
            notifier,
            acks,
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Loans a sample of `len` floats in shared memory, lets `fill` write the
    /// payload in place (no copy), checks it against `header`, sends it and
    /// wakes the receivers. Returns how many receivers got it.
    pub fn publish(
        &self,
        header: H,
        len: usize,
        fill: impl FnOnce(&mut [f32]),
    ) -> Result<usize, TransportError> {
        let expected = header.payload_len()?;
        if expected != len {
            return Err(poseflow_contracts::ContractError::PayloadLength {
                message: H::NAME,
                expected,
                actual: len,
            }
            .into());
        }
        let mut sample = self
            .publisher
            .loan_slice(len)
            .map_err(|e| TransportError::iceoryx("loan sample on", &self.name, e))?;
        *sample.user_header_mut() = header;
        fill(sample.payload_mut());
        let receivers = sample
            .send()
            .map_err(|e| TransportError::iceoryx("send on", &self.name, e))?;
        self.notify(events::DATA)?;
        Ok(receivers)
    }

    /// Tells receivers that no more samples follow and waits (up to
    /// `timeout`) until each has drained the edge and acknowledged.
    ///
    /// The wait matters: iceoryx2 frees a publisher's samples when it is
    /// dropped, so a stage that exits right after its last send would lose
    /// whatever its receivers had not yet taken.
    pub fn end_of_stream(
        &self,
        timeout: std::time::Duration,
    ) -> Result<EndOfStream, TransportError> {
        use iceoryx2::service::port_factory::PortFactory as _;
        let receivers = self.service.dynamic_config().number_of_subscribers();
        self.notify(events::END_OF_STREAM)?;
        let deadline = std::time::Instant::now() + timeout;
        let mut acknowledged = 0u64;
        while acknowledged < receivers as u64 {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() {
                tracing::warn!(edge = %self.name, receivers, acknowledged, "end-of-stream not acknowledged by every receiver in time");
                break;
            }
            self.acks
                .timed_wait(|activation| acknowledged += activation.count, left)
                .map_err(|e| {
                    TransportError::iceoryx("wait for acknowledgements on", &self.name, e)
                })?;
        }
        Ok(EndOfStream {
            receivers,
            acknowledged: acknowledged as usize,
        })
    }

    fn notify(&self, id: iceoryx2::port::event_id::EventId) -> Result<(), TransportError> {
        self.notifier
            .notify_with_custom_event_id(id)
            .map(|_| ())
            .map_err(|e| TransportError::iceoryx("notify on", &self.name, e))
    }
}

/// A received message: the contract header and the payload, still in shared
/// memory (released when dropped).
#[derive(Debug)]
pub struct Received<H: MessageHeader> {
    sample: Sample<Ipc, [f32], H>,
}

impl<H: MessageHeader> Received<H> {
    pub fn header(&self) -> &H {
        self.sample.user_header()
    }

    pub fn payload(&self) -> &[f32] {
        self.sample.payload()
    }
}

/// The receiving end of an edge. Attach it to a WaitSet
/// (`attach_notification`): it is woken by the publisher's events.
#[derive(Debug)]
pub struct EdgeSubscriber<H: MessageHeader> {
    name: String,
    subscriber: IoxSubscriber<Ipc, [f32], H>,
    listener: Listener<Ipc>,
    ack: Notifier<Ipc>,
}

impl<H: MessageHeader> FileDescriptorBased for EdgeSubscriber<H> {
    fn file_descriptor(&self) -> &FileDescriptor {
        self.listener.file_descriptor()
    }
}

impl<H: MessageHeader> SynchronousMultiplexing for EdgeSubscriber<H> {}

impl<H: MessageHeader> EdgeSubscriber<H> {
    pub fn create(node: &Node, name: &str, options: &EdgeOptions) -> Result<Self, TransportError> {
        let subscriber = open_pubsub::<H>(node, name, options)?
            .subscriber_builder()
            .buffer_size(options.queue)
            .create()
            .map_err(|e| TransportError::iceoryx("create subscriber on", name, e))?;
        let listener = open_event(node, name)?
            .listener_builder()
            .create()
            .map_err(|e| TransportError::iceoryx("create listener on", name, e))?;
        let ack = open_event(node, &ack_name(name))?
            .notifier_builder()
            .create()
            .map_err(|e| TransportError::iceoryx("create notifier on", name, e))?;
        Ok(Self {
            name: name.to_string(),
            subscriber,
            listener,
            ack,
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Consumes pending notifications; returns true when one of them was
    /// END_OF_STREAM.
    pub fn take_events(&self) -> Result<bool, TransportError> {
        let mut ended = false;
        self.listener
            .try_wait(|activation| ended |= activation.id == events::END_OF_STREAM)
            .map_err(|e| TransportError::iceoryx("wait on listener of", &self.name, e))?;
        Ok(ended)
    }

    /// Tells the publisher this receiver has drained the edge after its
    /// end-of-stream.
    pub fn acknowledge_end(&self) -> Result<(), TransportError> {
        self.ack
            .notify()
            .map(|_| ())
            .map_err(|e| TransportError::iceoryx("acknowledge end-of-stream on", &self.name, e))
    }

    /// The next queued message, if any. The header is not yet validated:
    /// call [`MessageHeader::check_payload`] before trusting the payload.
    pub fn receive(&self) -> Result<Option<Received<H>>, TransportError> {
        self.subscriber
            .receive()
            .map(|sample| sample.map(|sample| Received { sample }))
            .map_err(|e| TransportError::iceoryx("receive on", &self.name, e))
    }
}
