//! Edges whose message type is known only by name at run time, for the
//! processes that move messages without reading them: the launcher's
//! recorder and the Zenoh bridge. A message travels as its contract
//! header's raw bytes plus its payload; the header is checked against its
//! type's size and the payload against the header's counts on the way
//! back in.

use std::time::Duration;

use iceoryx2::prelude::{FileDescriptor, FileDescriptorBased, SynchronousMultiplexing};
use poseflow_contracts::{Header, MessageHeader, MessageVisitor, header_bytes, header_from_bytes, visit_message};

use crate::{EdgeOptions, EdgeSubscriber, EndOfStream, Node, Publisher, TransportError};

/// The receiving end of an edge of any message type.
pub trait UntypedSubscriber: FileDescriptorBased + SynchronousMultiplexing + std::fmt::Debug {
    fn edge(&self) -> &str;
    /// See [`EdgeSubscriber::take_events`].
    fn take_events(&self) -> Result<bool, TransportError>;
    fn acknowledge_end(&self) -> Result<(), TransportError>;
    /// Takes the next queued message, if any, and hands `each` its header's
    /// raw bytes and its payload (still in shared memory).
    fn receive_with(&self, each: &mut dyn FnMut(&[u8], &[f32])) -> Result<bool, TransportError>;
}

/// The sending end of an edge of any message type.
pub trait UntypedPublisher: std::fmt::Debug {
    fn edge(&self) -> &str;
    /// Publishes a message given as its header's raw bytes and its payload;
    /// returns the message's common header.
    fn publish_bytes(&self, header: &[u8], payload: &[f32]) -> Result<Header, TransportError>;
    /// See [`Publisher::wait_for_all_receivers_serving`].
    fn wait_for_all_receivers(&self, count: usize, warn_every: Duration) -> Result<usize, TransportError>;
    fn end_of_stream(&self, timeout: Duration) -> Result<EndOfStream, TransportError>;
}

#[derive(Debug)]
struct TypedSubscriber<H: MessageHeader>(EdgeSubscriber<H>);

impl<H: MessageHeader> FileDescriptorBased for TypedSubscriber<H> {
    fn file_descriptor(&self) -> &FileDescriptor {
        self.0.file_descriptor()
    }
}

impl<H: MessageHeader> SynchronousMultiplexing for TypedSubscriber<H> {}

impl<H: MessageHeader> UntypedSubscriber for TypedSubscriber<H> {
    fn edge(&self) -> &str {
        self.0.name()
    }

    fn take_events(&self) -> Result<bool, TransportError> {
        self.0.take_events()
    }

    fn acknowledge_end(&self) -> Result<(), TransportError> {
        self.0.acknowledge_end()
    }

    fn receive_with(&self, each: &mut dyn FnMut(&[u8], &[f32])) -> Result<bool, TransportError> {
        let Some(message) = self.0.receive()? else { return Ok(false) };
        each(&header_bytes(message.header()), message.payload());
        Ok(true)
    }
}

#[derive(Debug)]
struct TypedPublisher<H: MessageHeader>(Publisher<H>);

impl<H: MessageHeader> UntypedPublisher for TypedPublisher<H> {
    fn edge(&self) -> &str {
        self.0.name()
    }

    fn publish_bytes(&self, header: &[u8], payload: &[f32]) -> Result<Header, TransportError> {
        let header = header_from_bytes::<H>(header).ok_or(TransportError::HeaderSize {
            message: H::NAME,
            expected: std::mem::size_of::<H>(),
            found: header.len(),
        })?;
        self.0.publish(header, payload.len(), |out| out.copy_from_slice(payload))?;
        Ok(*header.header())
    }

    fn wait_for_all_receivers(&self, count: usize, warn_every: Duration) -> Result<usize, TransportError> {
        self.0.wait_for_all_receivers_serving(count, warn_every, &mut || {})
    }

    fn end_of_stream(&self, timeout: Duration) -> Result<EndOfStream, TransportError> {
        self.0.end_of_stream(timeout)
    }
}

/// Which end of an edge to open, and where.
struct Open<'a> {
    node: &'a Node,
    service: &'a str,
    options: &'a EdgeOptions,
}

struct Subscribe<'a>(Open<'a>);
struct Publish<'a>(Open<'a>);

impl MessageVisitor for Subscribe<'_> {
    type Output = Result<Box<dyn UntypedSubscriber>, TransportError>;

    fn visit<H: MessageHeader + Send + 'static>(self) -> Self::Output {
        let Open { node, service, options } = self.0;
        Ok(Box::new(TypedSubscriber(EdgeSubscriber::<H>::create(node, service, options)?)))
    }
}

impl MessageVisitor for Publish<'_> {
    type Output = Result<Box<dyn UntypedPublisher>, TransportError>;

    fn visit<H: MessageHeader + Send + 'static>(self) -> Self::Output {
        let Open { node, service, options } = self.0;
        Ok(Box::new(TypedPublisher(Publisher::<H>::create(node, service, options)?)))
    }
}

/// Subscribes to `service`, an edge carrying contract message `message`.
pub fn untyped_subscriber(
    node: &Node,
    message: &str,
    service: &str,
    options: &EdgeOptions,
) -> Result<Box<dyn UntypedSubscriber>, TransportError> {
    by_name(message, Subscribe(Open { node, service, options }))
}

/// Publishes on `service`, an edge carrying contract message `message`.
pub fn untyped_publisher(
    node: &Node,
    message: &str,
    service: &str,
    options: &EdgeOptions,
) -> Result<Box<dyn UntypedPublisher>, TransportError> {
    by_name(message, Publish(Open { node, service, options }))
}

/// Runs `visitor` with the header type named `message`.
fn by_name<T>(
    message: &str,
    visitor: impl MessageVisitor<Output = Result<T, TransportError>>,
) -> Result<T, TransportError> {
    visit_message(message, visitor)
        .unwrap_or_else(|| Err(TransportError::UnknownMessage { message: message.to_string() }))
}
