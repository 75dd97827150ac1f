//! Publish-subscribe of contract messages (`H` user header + `[f32]`
//! payload), with event notifications for wake-up and two handshakes:
//! READY (a receiver is connected before a publisher starts) and
//! END_OF_STREAM / END_ACKNOWLEDGED (receivers drained before a publisher
//! exits).

use std::time::{Duration, Instant};

use iceoryx2::port::event_id::EventId;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher as IoxPublisher;
use iceoryx2::port::subscriber::Subscriber as IoxSubscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::{
    AllocationStrategy, BackpressureStrategy, FileDescriptor, FileDescriptorBased, SynchronousMultiplexing,
};
use iceoryx2::sample::Sample;
use iceoryx2::service::port_factory::PortFactory as _;
use iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory;
use poseflow_contracts::{ContractError, MessageHeader};

use crate::{Ipc, Node, TransportError, blocked, termination_requested};

/// Event ids. Each edge has two event services: `<edge>` (publisher →
/// receivers) and `<edge>/ack` (receivers → publisher).
pub mod events {
    use iceoryx2::port::event_id::EventId;

    /// `<edge>`: a new sample was published.
    pub const DATA: EventId = EventId::new(0);
    /// `<edge>`: the publisher has sent its last sample; receivers drain and
    /// finish.
    pub const END_OF_STREAM: EventId = EventId::new(1);
    /// `<edge>`: a publisher appeared (emitted by iceoryx2 when its notifier
    /// is created); receivers connect to it and answer READY.
    pub const PUBLISHER_CONNECTED: EventId = EventId::new(2);
    /// `<edge>/ack`: a receiver drained the edge after END_OF_STREAM.
    pub const END_ACKNOWLEDGED: EventId = EventId::new(0);
    /// `<edge>/ack`: a receiver is connected and will see every sample.
    pub const READY: EventId = EventId::new(1);
    /// Highest id in use (sizes the event services).
    pub const MAX: usize = 2;
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
    /// Largest payload, in `f32` values. Shared memory for it is reserved up
    /// front: iceoryx2's growing segments lose samples when a publisher
    /// reallocates and exits before receivers have mapped the new segment.
    pub max_payload_len: usize,
}

impl Default for EdgeOptions {
    fn default() -> Self {
        Self { queue: 4, overflow: Overflow::DropOldest, max_payload_len: 4096 }
    }
}

/// Ports of a restarted process coexist briefly with its dead predecessor's
/// until stale resources are removed, so capacities leave room for that.
const MAX_PUBLISHERS: usize = 4;
const MAX_SUBSCRIBERS: usize = 16;
const MAX_NODES: usize = 32;

pub(crate) fn service_name(name: &str) -> Result<iceoryx2::prelude::ServiceName, TransportError> {
    name.try_into().map_err(|e| TransportError::Name { name: name.to_string(), detail: format!("{e:?}") })
}

fn open_pubsub<H: MessageHeader>(
    node: &Node,
    name: &str,
    options: &EdgeOptions,
) -> Result<PortFactory<Ipc, [f32], H>, TransportError> {
    node.service_builder(&service_name(name)?)
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

pub(crate) fn open_event(node: &Node, name: &str) -> Result<EventFactory<Ipc>, TransportError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_notifiers(MAX_SUBSCRIBERS)
        .max_listeners(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .event_id_max_value(events::MAX)
        .notifier_created_event(events::PUBLISHER_CONNECTED)
        .open_or_create()
        .map_err(|e| TransportError::iceoryx("open event service", name, e))
}

/// A listener on the event service `name`.
pub(crate) fn listener(node: &Node, name: &str) -> Result<Listener<Ipc>, TransportError> {
    open_event(node, name)?
        .listener_builder()
        .create()
        .map_err(|e| TransportError::iceoryx("create listener on", name, e))
}

/// A notifier on the event service `name`.
pub(crate) fn notifier(node: &Node, name: &str) -> Result<Notifier<Ipc>, TransportError> {
    open_event(node, name)?
        .notifier_builder()
        .create()
        .map_err(|e| TransportError::iceoryx("create notifier on", name, e))
}

fn ack_name(edge: &str) -> String {
    format!("{edge}/ack")
}

fn notify(notifier: &Notifier<Ipc>, id: EventId, what: &'static str, edge: &str) -> Result<(), TransportError> {
    notifier.notify_with_custom_event_id(id).map(|_| ()).map_err(|e| TransportError::iceoryx(what, edge, e))
}

/// How an end-of-stream handshake ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EndOfStream {
    /// Receivers connected when the stream ended.
    pub receivers: usize,
    /// Receivers that acknowledged having drained the edge in time.
    pub acknowledged: usize,
}

/// How often a draining publisher hands control back to its stage.
const SERVE_SLICE: Duration = Duration::from_millis(5);

/// The sending end of an edge.
#[derive(Debug)]
pub struct Publisher<H: MessageHeader> {
    name: String,
    service: PortFactory<Ipc, [f32], H>,
    publisher: IoxPublisher<Ipc, [f32], H>,
    notifier: Notifier<Ipc>,
    acks: Listener<Ipc>,
    max_payload_len: usize,
    /// READY notifications seen so far. A receiver may say READY more than
    /// once (at creation and on seeing this publisher appear), so receivers
    /// count as ready only up to the number of subscribers.
    ready_acks: std::cell::Cell<usize>,
    overflow: Overflow,
    /// Readers found ready by the last wait for them. On a `block` edge a
    /// send waits while fewer are connected: a reader being replaced by the
    /// supervisor would otherwise miss every sample sent before its
    /// replacement subscribes.
    readers: std::cell::Cell<usize>,
    /// Whether the last send reached fewer readers than `readers`.
    short: std::cell::Cell<bool>,
}

/// How long a blocked send waits before it is logged.
const LONG_BLOCK: Duration = Duration::from_secs(2);

/// How long a start-up wait may last.
enum Patience {
    /// Give up at this instant.
    Until(Instant),
    /// Never give up; warn this often.
    Forever { warn_every: Duration },
}

impl<H: MessageHeader> Publisher<H> {
    pub fn create(node: &Node, name: &str, options: &EdgeOptions) -> Result<Self, TransportError> {
        let service = open_pubsub::<H>(node, name, options)?;
        let backpressure = match options.overflow {
            Overflow::DropOldest => BackpressureStrategy::DiscardData,
            Overflow::Block => BackpressureStrategy::RetryUntilDelivered,
        };
        let max_payload_len = options.max_payload_len.max(1);
        let mut builder = service
            .publisher_builder()
            .initial_max_slice_len(max_payload_len)
            .allocation_strategy(AllocationStrategy::Static)
            .backpressure_strategy(backpressure);
        if options.overflow == Overflow::Block {
            builder = builder.set_backpressure_handler(blocked::on_backpressure);
        }
        let publisher = builder.create().map_err(|e| TransportError::iceoryx("create publisher on", name, e))?;
        // The ack listener exists before the notifier announces this publisher,
        // so no READY is missed.
        let acks = listener(node, &ack_name(name))?;
        let notifier = notifier(node, name)?;
        Ok(Self {
            name: name.to_string(),
            service,
            publisher,
            notifier,
            acks,
            max_payload_len,
            ready_acks: std::cell::Cell::new(0),
            overflow: options.overflow,
            readers: std::cell::Cell::new(0),
            short: std::cell::Cell::new(false),
        })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Loans a sample of `len` floats in shared memory, lets `fill` write the
    /// payload in place (no copy), checks it against `header`, sends it and
    /// wakes the receivers. Returns how many receivers got it.
    ///
    /// The loaned memory is not cleared: until `fill` writes it, it holds an
    /// earlier sample's values, so `fill` must write every element.
    ///
    /// On a `block` edge whose readers were waited for, a send also waits
    /// while one of them is gone (killed, being replaced): it goes out once
    /// the replacement has said READY. A send that reached no reader because
    /// its reader died meanwhile is sent again the same way.
    pub fn publish(&self, header: H, len: usize, fill: impl FnMut(&mut [f32])) -> Result<usize, TransportError> {
        self.publish_serving(header, len, fill, &mut || {})
    }

    /// As [`Self::publish`]; while the send waits on a full queue (`block`
    /// overflow) or for a replaced reader, calls `meanwhile` between
    /// retries. A stage that answers requests passes its request handler,
    /// so its readers' calls are answered while it waits for them to read.
    pub fn publish_serving(
        &self,
        header: H,
        len: usize,
        mut fill: impl FnMut(&mut [f32]),
        meanwhile: &mut dyn FnMut(),
    ) -> Result<usize, TransportError> {
        let expected = header.payload_len()?;
        if expected != len {
            return Err(ContractError::PayloadLength { message: H::NAME, expected, actual: len }.into());
        }
        if len > self.max_payload_len {
            return Err(TransportError::PayloadTooLarge { len, max: self.max_payload_len });
        }
        loop {
            self.wait_for_replaced_readers(meanwhile)?;
            let receivers = self.send_once(header, len, &mut fill, meanwhile)?;
            if receivers > 0 || !self.waits_for_readers() || termination_requested() {
                return Ok(receivers);
            }
            tracing::warn!(edge = %self.name, "the reader went away during the send; sending again once it is replaced");
        }
    }

    /// Readers found ready by the last wait for them (0 before any wait).
    pub fn readers(&self) -> usize {
        self.readers.get()
    }

    /// Whether a send that reached `receivers` missed one of the readers
    /// (a `drop-oldest` edge while its reader is replaced; a `block` edge
    /// with several readers when one died during the send). The first miss
    /// of a run is logged.
    pub fn missed_a_reader(&self, receivers: usize) -> bool {
        let readers = self.readers.get();
        let short = receivers < readers;
        if short && !self.short.get() {
            tracing::warn!(edge = %self.name, receivers, readers, "sends miss a reader (gone, being replaced); each is counted as dropped");
        }
        self.short.set(short);
        short
    }

    fn waits_for_readers(&self) -> bool {
        self.overflow == Overflow::Block && self.readers.get() > 0
    }

    /// On a `block` edge, waits while fewer readers are connected than were
    /// ready before, until the missing ones' replacements say READY (or
    /// SIGINT/SIGTERM arrived).
    fn wait_for_replaced_readers(&self, meanwhile: &mut dyn FnMut()) -> Result<(), TransportError> {
        if !self.waits_for_readers() {
            return Ok(());
        }
        let readers = self.readers.get();
        let connected = self.service.dynamic_config().number_of_subscribers();
        if connected >= readers {
            return Ok(());
        }
        tracing::warn!(edge = %self.name, connected, readers, "a reader is gone; sends wait until it is replaced");
        // Those still connected are ready; each replacement must say so.
        self.ready_acks.set(connected);
        let ready = self.wait_ready(readers, Patience::Forever { warn_every: LONG_BLOCK }, meanwhile)?;
        tracing::info!(edge = %self.name, ready, "a replaced reader is ready; sends resume");
        Ok(())
    }

    /// One loan, fill and send; how many receivers got the sample.
    fn send_once(
        &self,
        header: H,
        len: usize,
        fill: &mut dyn FnMut(&mut [f32]),
        meanwhile: &mut dyn FnMut(),
    ) -> Result<usize, TransportError> {
        let mut sample = self
            .publisher
            .loan_slice_uninit(len)
            .map_err(|e| TransportError::iceoryx("loan sample on", &self.name, e))?;
        *sample.user_header_mut() = header;
        let payload = sample.payload_mut();
        // SAFETY: the loaned chunk lies in a shared-memory segment that the
        // kernel zero-filled when it was created and that only ever holds f32
        // values written by earlier samples, so every byte is initialised; we
        // skip `loan_slice`'s memset, which costs more than the whole
        // transfer at megabyte sizes. `fill` overwrites the payload before it
        // is sent.
        let floats = unsafe { std::slice::from_raw_parts_mut(payload.as_mut_ptr().cast::<f32>(), payload.len()) };
        fill(floats);
        // SAFETY: as above, the memory holds initialised f32 values.
        let sample = unsafe { sample.assume_init() };
        // A send held back this long is logged, and again each time the wait
        // doubles: a graph that stops moving says which edge it waits on.
        let (blocked_since, mut report_at) = (Instant::now(), LONG_BLOCK);
        let mut meanwhile = || {
            if blocked_since.elapsed() >= report_at {
                tracing::warn!(edge = %self.name, waited_s = report_at.as_secs(), "a send is held back by a reader's full queue");
                report_at *= 2;
            }
            meanwhile();
        };
        let receivers = blocked::while_blocked(&mut meanwhile, || sample.send())
            .map_err(|e| TransportError::iceoryx("send on", &self.name, e))?;
        notify(&self.notifier, events::DATA, "notify on", &self.name)?;
        Ok(receivers)
    }

    /// Waits (up to `timeout`) until `count` receivers have connected and
    /// said READY.
    ///
    /// iceoryx2 completes a connection only when the receiver next touches
    /// its port, and a blocking send into a half-made connection is dropped;
    /// so a fast source must not start before its readers answer. Returns
    /// how many answered.
    pub fn wait_for_receivers(&self, count: usize, timeout: Duration) -> Result<usize, TransportError> {
        self.wait_for_receivers_serving(count, timeout, &mut || {})
    }

    /// As [`Self::wait_for_receivers`], calling `meanwhile` every few
    /// milliseconds: a stage whose reader is also its writer (a loop) keeps
    /// answering that reader's own handshake while it waits.
    pub fn wait_for_receivers_serving(
        &self,
        count: usize,
        timeout: Duration,
        meanwhile: &mut dyn FnMut(),
    ) -> Result<usize, TransportError> {
        self.wait_ready(count, Patience::Until(Instant::now() + timeout), meanwhile)
    }

    /// As [`Self::wait_for_receivers_serving`] with no deadline: waits
    /// until all `count` receivers are ready or SIGINT/SIGTERM arrived,
    /// warning every `warn_every` meanwhile. A graph stage uses it: its
    /// readers may take long to start (a selector precomputing distance
    /// grids), and a publisher that went ahead without them would send into
    /// half-made connections, which iceoryx2 drops without a trace.
    pub fn wait_for_all_receivers_serving(
        &self,
        count: usize,
        warn_every: Duration,
        meanwhile: &mut dyn FnMut(),
    ) -> Result<usize, TransportError> {
        self.wait_ready(count, Patience::Forever { warn_every }, meanwhile)
    }

    /// Receivers that said READY, at most one per subscriber connected now.
    fn ready_receivers(&self) -> usize {
        self.ready_acks.get().min(self.service.dynamic_config().number_of_subscribers())
    }

    fn wait_ready(
        &self,
        count: usize,
        patience: Patience,
        meanwhile: &mut dyn FnMut(),
    ) -> Result<usize, TransportError> {
        self.connect()?;
        let mut last_warning = Instant::now();
        loop {
            let ready = self.ready_receivers();
            let out_of_time = match patience {
                Patience::Until(deadline) => Instant::now() >= deadline,
                Patience::Forever { warn_every } => {
                    if last_warning.elapsed() >= warn_every {
                        tracing::warn!(edge = %self.name, ready, expected = count, "still waiting for every reader to connect");
                        last_warning = Instant::now();
                    }
                    false
                }
            };
            if ready >= count || out_of_time || termination_requested() {
                self.connect()?;
                self.readers.set(ready);
                return Ok(ready);
            }
            let seen = self.wait_for_acks(events::READY, 1, SERVE_SLICE * 10, meanwhile)?;
            if seen > 0 {
                tracing::debug!(edge = %self.name, ready = self.ready_receivers(), expected = count, "a reader said READY");
            }
            self.ready_acks.set(self.ready_acks.get() + seen);
        }
    }

    /// Tells receivers that no more samples follow and waits (up to
    /// `timeout`) until each has drained the edge and acknowledged.
    ///
    /// The wait matters: iceoryx2 frees a publisher's samples when it is
    /// dropped, so a stage that exits right after its last send would lose
    /// whatever its receivers had not yet taken.
    pub fn end_of_stream(&self, timeout: Duration) -> Result<EndOfStream, TransportError> {
        self.end_of_stream_serving(timeout, || Ok(()))
    }

    /// As [`Self::end_of_stream`], calling `meanwhile` every few milliseconds
    /// while it waits: a stage that also answers requests keeps answering
    /// them, since its readers may need answers before they can finish.
    pub fn end_of_stream_serving(
        &self,
        timeout: Duration,
        mut meanwhile: impl FnMut() -> Result<(), TransportError>,
    ) -> Result<EndOfStream, TransportError> {
        let receivers = self.service.dynamic_config().number_of_subscribers();
        notify(&self.notifier, events::END_OF_STREAM, "notify on", &self.name)?;
        let mut acknowledged = 0;
        let deadline = Instant::now() + timeout;
        while acknowledged < receivers {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() || termination_requested() {
                break;
            }
            meanwhile()?;
            acknowledged += self.wait_for_acks(
                events::END_ACKNOWLEDGED,
                receivers - acknowledged,
                left.min(SERVE_SLICE),
                &mut || {},
            )?;
        }
        if acknowledged < receivers {
            tracing::warn!(edge = %self.name, receivers, acknowledged, "end-of-stream not acknowledged by every receiver in time");
        }
        Ok(EndOfStream { receivers, acknowledged })
    }

    fn connect(&self) -> Result<(), TransportError> {
        self.publisher.update_connections().map_err(|e| TransportError::iceoryx("connect receivers of", &self.name, e))
    }

    /// Counts `id` notifications on the ack service until `count` arrived,
    /// `timeout` passed or SIGINT/SIGTERM arrived; other ids are discarded.
    fn wait_for_acks(
        &self,
        id: EventId,
        count: usize,
        timeout: Duration,
        meanwhile: &mut dyn FnMut(),
    ) -> Result<usize, TransportError> {
        // Short slices, so a termination request is noticed promptly.
        const SLICE: Duration = Duration::from_millis(50);
        let deadline = Instant::now() + timeout;
        let mut seen = 0u64;
        while seen < count as u64 {
            let left = deadline.saturating_duration_since(Instant::now()).min(SLICE);
            if left.is_zero() || termination_requested() {
                break;
            }
            meanwhile();
            self.acks
                .timed_wait(
                    |activation| {
                        if activation.id == id {
                            seen += activation.count;
                        }
                    },
                    left,
                )
                .map_err(|e| TransportError::iceoryx("wait for receivers on", &self.name, e))?;
        }
        Ok(seen as usize)
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
        // The listener exists before the subscriber: a running writer sends
        // to a new subscriber at once, and a DATA event sent before the
        // listener existed would be lost while the queue stays full: the
        // writer blocked on it, this reader asleep (a restarted selector
        // and its sampler, in the soak).
        let listener = listener(node, name)?;
        let subscriber = open_pubsub::<H>(node, name, options)?
            .subscriber_builder()
            .buffer_size(options.queue)
            .create()
            .map_err(|e| TransportError::iceoryx("create subscriber on", name, e))?;
        let ack = notifier(node, &ack_name(name))?;
        let edge = Self { name: name.to_string(), subscriber, listener, ack };
        edge.connect()?;
        Ok(edge)
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Connects to every publisher now present and tells them READY.
    fn connect(&self) -> Result<(), TransportError> {
        self.subscriber
            .update_connections()
            .map_err(|e| TransportError::iceoryx("connect to publishers of", &self.name, e))?;
        notify(&self.ack, events::READY, "signal ready on", &self.name)
    }

    /// Consumes pending notifications (connecting to new publishers on the
    /// way); returns true when one of them was END_OF_STREAM.
    pub fn take_events(&self) -> Result<bool, TransportError> {
        let (mut ended, mut new_publisher) = (false, false);
        self.listener
            .try_wait(|activation| {
                ended |= activation.id == events::END_OF_STREAM;
                new_publisher |= activation.id == events::PUBLISHER_CONNECTED;
            })
            .map_err(|e| TransportError::iceoryx("wait on listener of", &self.name, e))?;
        if new_publisher {
            tracing::debug!(edge = %self.name, "a writer appeared; answering its handshake");
            self.connect()?;
        }
        Ok(ended)
    }

    /// Tells the publisher this receiver has drained the edge after its
    /// end-of-stream.
    pub fn acknowledge_end(&self) -> Result<(), TransportError> {
        notify(&self.ack, events::END_ACKNOWLEDGED, "acknowledge end-of-stream on", &self.name)
    }

    /// Whether a message is queued (connecting to new writers on the way).
    pub fn has_messages(&self) -> Result<bool, TransportError> {
        self.subscriber.has_samples().map_err(|e| TransportError::iceoryx("look for messages on", &self.name, e))
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
