//! Request-response with `[f32]` payloads and contract headers, woken by
//! events: the sampler ⇄ inference velocity loop (one request per Euler
//! step, N poses in, N velocities out).
//!
//! Services for an edge `<edge>`: the request-response service itself, an
//! event service `<edge>` on which clients announce requests, and
//! `<edge>/response` on which servers announce responses.

use std::time::{Duration, Instant};

use iceoryx2::active_request::ActiveRequest;
use iceoryx2::port::client::Client;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::server::Server;
use iceoryx2::prelude::{AllocationStrategy, FileDescriptor, FileDescriptorBased, SynchronousMultiplexing};
use iceoryx2::response::Response;
use iceoryx2::service::port_factory::request_response::PortFactory;
use poseflow_contracts::{ContractError, MessageHeader};

use crate::pubsub::{events, listener, notifier, service_name};
use crate::{Ipc, Node, TransportError, termination_requested};

fn response_events(edge: &str) -> String {
    format!("{edge}/response")
}

/// The request-response service of an edge: `[f32]` both ways.
type Service<Req, Resp> = PortFactory<Ipc, [f32], Req, [f32], Resp>;

fn open<Req: MessageHeader, Resp: MessageHeader>(
    node: &Node,
    name: &str,
) -> Result<Service<Req, Resp>, TransportError> {
    node.service_builder(&service_name(name)?)
        .request_response::<[f32], [f32]>()
        .request_user_header::<Req>()
        .response_user_header::<Resp>()
        .max_clients(4)
        .max_servers(4)
        .max_nodes(32)
        .max_active_requests_per_client(2)
        .max_response_buffer_size(2)
        .open_or_create()
        .map_err(|e| TransportError::iceoryx("open request-response service", name, e))
}

/// Writes `len` floats in place into loaned memory, checked against `header`.
fn check_len<H: MessageHeader>(header: &H, len: usize, max: usize) -> Result<(), TransportError> {
    let expected = header.payload_len()?;
    if expected != len {
        return Err(ContractError::PayloadLength { message: H::NAME, expected, actual: len }.into());
    }
    if len > max {
        return Err(TransportError::PayloadTooLarge { len, max });
    }
    Ok(())
}

/// A response still in shared memory.
#[derive(Debug)]
pub struct Reply<Req: MessageHeader, Resp: MessageHeader> {
    response: Response<Ipc, [f32], Resp>,
    _request: std::marker::PhantomData<fn() -> Req>,
}

impl<Req: MessageHeader, Resp: MessageHeader> Reply<Req, Resp> {
    pub fn header(&self) -> &Resp {
        self.response.user_header()
    }

    pub fn payload(&self) -> &[f32] {
        self.response.payload()
    }
}

/// How often a waiting caller checks that a server still holds its request.
const SERVER_CHECK_EVERY: Duration = Duration::from_millis(50);

/// The calling side (the sampler).
#[derive(Debug)]
pub struct RequestClient<Req: MessageHeader, Resp: MessageHeader> {
    name: String,
    client: Client<Ipc, [f32], Req, [f32], Resp>,
    requests: Notifier<Ipc>,
    responses: Listener<Ipc>,
    max_request_len: usize,
}

impl<Req: MessageHeader, Resp: MessageHeader> RequestClient<Req, Resp> {
    pub fn create(node: &Node, name: &str, max_request_len: usize) -> Result<Self, TransportError> {
        let max_request_len = max_request_len.max(1);
        let client = open::<Req, Resp>(node, name)?
            .client_builder()
            .initial_max_slice_len(max_request_len)
            .allocation_strategy(AllocationStrategy::Static)
            .create()
            .map_err(|e| TransportError::iceoryx("create client on", name, e))?;
        let responses = listener(node, &response_events(name))?;
        let requests = notifier(node, name)?;
        Ok(Self { name: name.to_string(), client, requests, responses, max_request_len })
    }

    /// Sends a request whose payload `fill` writes in place, then sleeps
    /// until the response arrives or `timeout` passes.
    pub fn call(
        &self,
        header: Req,
        len: usize,
        fill: impl FnOnce(&mut [f32]),
        timeout: Duration,
    ) -> Result<Reply<Req, Resp>, TransportError> {
        check_len(&header, len, self.max_request_len)?;
        // A stopping caller would otherwise wait out the timeout once per
        // request still queued: iceoryx2 interrupts only the first wait.
        if termination_requested() {
            return Err(TransportError::Interrupted { operation: "request", target: self.name.clone() });
        }
        let mut request = self
            .client
            .loan_slice_uninit(len)
            .map_err(|e| TransportError::iceoryx("loan request on", &self.name, e))?;
        *request.user_header_mut() = header;
        let payload = request.payload_mut();
        // SAFETY: as for publish-subscribe loans: the chunk lies in a
        // kernel-zeroed segment that only ever holds f32 values, so every
        // byte is initialised; `fill` overwrites it before sending.
        fill(unsafe { std::slice::from_raw_parts_mut(payload.as_mut_ptr().cast::<f32>(), payload.len()) });
        // SAFETY: see above.
        let request = unsafe { request.assume_init() };
        let pending = request.send().map_err(|e| TransportError::iceoryx("send request on", &self.name, e))?;
        self.requests
            .notify_with_custom_event_id(events::DATA)
            .map_err(|e| TransportError::iceoryx("notify server on", &self.name, e))?;
        let sent_at = Instant::now();
        let deadline = sent_at + timeout;
        let mut report_at = LONG_WAIT;
        loop {
            if sent_at.elapsed() >= report_at {
                tracing::warn!(edge = %self.name, waited_s = report_at.as_secs(), "a request is still unanswered");
                report_at *= 2;
            }
            // Read before `receive`, which updates the connections: a response
            // sent just before its server went away is still taken below.
            let server_gone = !pending.is_connected();
            if let Some(response) =
                pending.receive().map_err(|e| TransportError::iceoryx("receive response on", &self.name, e))?
            {
                return Ok(Reply { response, _request: std::marker::PhantomData });
            }
            if termination_requested() {
                return Err(TransportError::Interrupted { operation: "response", target: self.name.clone() });
            }
            // A server that died (and was cleaned up) or dropped the request
            // answers nothing: waiting out the timeout would only stall.
            if server_gone {
                return Err(TransportError::NoServer { target: self.name.clone() });
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(TransportError::Timeout {
                    operation: "response",
                    target: self.name.clone(),
                    after: timeout,
                });
            }
            // A dead server sends no event: look again every slice.
            self.responses
                .timed_wait(|_| {}, left.min(SERVER_CHECK_EVERY))
                .map_err(|e| TransportError::iceoryx("wait for response on", &self.name, e))?;
        }
    }
}

/// How long an unanswered request waits before it is logged (and again
/// each time the wait doubles, until its timeout).
const LONG_WAIT: Duration = Duration::from_secs(2);

/// Sends one response to the request being handled.
#[derive(Debug)]
pub struct Responder<'a, Req: MessageHeader, Resp: MessageHeader> {
    request: &'a ActiveRequest<Ipc, [f32], Req, [f32], Resp>,
    name: &'a str,
    max_response_len: usize,
    sent: bool,
}

impl<Req: MessageHeader, Resp: MessageHeader> Responder<'_, Req, Resp> {
    pub fn send(&mut self, header: Resp, len: usize, fill: impl FnOnce(&mut [f32])) -> Result<(), TransportError> {
        check_len(&header, len, self.max_response_len)?;
        let mut response = self
            .request
            .loan_slice_uninit(len)
            .map_err(|e| TransportError::iceoryx("loan response on", self.name, e))?;
        *response.user_header_mut() = header;
        let payload = response.payload_mut();
        // SAFETY: as in `RequestClient::call`.
        fill(unsafe { std::slice::from_raw_parts_mut(payload.as_mut_ptr().cast::<f32>(), payload.len()) });
        // SAFETY: see above.
        let response = unsafe { response.assume_init() };
        response.send().map_err(|e| TransportError::iceoryx("send response on", self.name, e))?;
        self.sent = true;
        Ok(())
    }
}

/// The answering side (the inference stage). Attach it to a WaitSet.
#[derive(Debug)]
pub struct RequestServer<Req: MessageHeader, Resp: MessageHeader> {
    name: String,
    server: Server<Ipc, [f32], Req, [f32], Resp>,
    requests: Listener<Ipc>,
    responses: Notifier<Ipc>,
    max_response_len: usize,
}

impl<Req: MessageHeader, Resp: MessageHeader> FileDescriptorBased for RequestServer<Req, Resp> {
    fn file_descriptor(&self) -> &FileDescriptor {
        self.requests.file_descriptor()
    }
}

impl<Req: MessageHeader, Resp: MessageHeader> SynchronousMultiplexing for RequestServer<Req, Resp> {}

impl<Req: MessageHeader, Resp: MessageHeader> RequestServer<Req, Resp> {
    pub fn create(node: &Node, name: &str, max_response_len: usize) -> Result<Self, TransportError> {
        let max_response_len = max_response_len.max(1);
        let server = open::<Req, Resp>(node, name)?
            .server_builder()
            .initial_max_slice_len(max_response_len)
            .allocation_strategy(AllocationStrategy::Static)
            .create()
            .map_err(|e| TransportError::iceoryx("create server on", name, e))?;
        let requests = listener(node, name)?;
        let responses = notifier(node, &response_events(name))?;
        Ok(Self { name: name.to_string(), server, requests, responses, max_response_len })
    }

    /// Answers every queued request with `handle(header, payload, responder)`;
    /// the handler validates the request itself (e.g. answering with an
    /// error status). Returns how many requests were handled.
    pub fn serve(
        &self,
        mut handle: impl FnMut(&Req, &[f32], &mut Responder<'_, Req, Resp>) -> Result<(), TransportError>,
    ) -> Result<usize, TransportError> {
        self.requests.try_wait(|_| {}).map_err(|e| TransportError::iceoryx("wait on listener of", &self.name, e))?;
        let mut handled = 0;
        while let Some(request) =
            self.server.receive().map_err(|e| TransportError::iceoryx("receive request on", &self.name, e))?
        {
            let mut responder =
                Responder { request: &request, name: &self.name, max_response_len: self.max_response_len, sent: false };
            handle(request.user_header(), request.payload(), &mut responder)?;
            if responder.sent {
                self.responses
                    .notify_with_custom_event_id(events::DATA)
                    .map_err(|e| TransportError::iceoryx("notify client on", &self.name, e))?;
            }
            handled += 1;
        }
        tracing::trace!(service = %self.name, handled, "served");
        Ok(handled)
    }
}
