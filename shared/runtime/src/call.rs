//! The calling side of a request-response edge, whichever way the graph
//! runs: over iceoryx2 between processes, or to the serving stage's thread
//! when the graph runs in-process. A stage asks [`connect`] for its client
//! and never learns which one it got.

use std::any::Any;
use std::collections::HashMap;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use poseflow_contracts::MessageHeader;
use poseflow_graph::EdgeWiring;
use poseflow_transport::{Node, RequestClient, TransportError, create_node};

use crate::local::queue::Doorbell;

/// Why a call got no answer.
#[derive(Debug, thiserror::Error)]
pub enum CallError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error("no response on `{edge}` within {after:?}")]
    Timeout { edge: String, after: Duration },
    #[error("the server of `{edge}` has stopped")]
    ServerGone { edge: String },
    #[error("edge `{edge}` serves other message types than {expected} expected by this caller")]
    MessageType { edge: String, expected: &'static str },
}

/// A client of one request-response edge.
pub trait Call<Req: MessageHeader, Resp: MessageHeader>: std::fmt::Debug {
    /// Sends `header` with `payload`, waits at most `timeout` for the
    /// response and hands it to `on_reply`.
    fn call(
        &mut self,
        header: Req,
        payload: &[f32],
        timeout: Duration,
        on_reply: &mut dyn FnMut(&Resp, &[f32]),
    ) -> Result<(), CallError>;
}

/// The client of `edge` for the stage `stage`: the in-process server's if
/// an in-process graph serves that edge, else an iceoryx2 client.
pub fn connect<Req, Resp>(stage: &str, edge: &EdgeWiring) -> Result<Box<dyn Call<Req, Resp>>, CallError>
where
    Req: MessageHeader + Send + 'static,
    Resp: MessageHeader + Send + 'static,
{
    if let Some(endpoint) = endpoints().lock().unwrap_or_else(|e| e.into_inner()).get(&edge.service) {
        let endpoint = endpoint
            .clone()
            .downcast::<Endpoint<Req, Resp>>()
            .map_err(|_| CallError::MessageType { edge: edge.edge.clone(), expected: Req::NAME })?;
        endpoint.clients.fetch_add(1, Ordering::SeqCst);
        return Ok(Box::new(LocalCaller { edge: edge.edge.clone(), endpoint }));
    }
    let node = create_node(&format!("{stage}-{}", edge.edge))?;
    let client = RequestClient::create(&node, &edge.service, edge.max_payload_len)?;
    Ok(Box::new(IpcCaller { client, _node: node }))
}

#[derive(Debug)]
struct IpcCaller<Req: MessageHeader, Resp: MessageHeader> {
    // Declared before the node it was created on, so it is dropped first.
    client: RequestClient<Req, Resp>,
    _node: Node,
}

impl<Req: MessageHeader, Resp: MessageHeader> Call<Req, Resp> for IpcCaller<Req, Resp> {
    fn call(
        &mut self,
        header: Req,
        payload: &[f32],
        timeout: Duration,
        on_reply: &mut dyn FnMut(&Resp, &[f32]),
    ) -> Result<(), CallError> {
        let reply = self.client.call(header, payload.len(), |buffer| buffer.copy_from_slice(payload), timeout)?;
        on_reply(reply.header(), reply.payload());
        Ok(())
    }
}

/// One request waiting for the in-process server, with where its answer goes.
pub(crate) struct PendingRequest<Req, Resp> {
    pub header: Req,
    pub payload: Vec<f32>,
    pub reply: mpsc::SyncSender<(Resp, Vec<f32>)>,
}

/// An in-process server's request queue.
pub(crate) struct Endpoint<Req, Resp> {
    pub requests: Mutex<VecDeque<PendingRequest<Req, Resp>>>,
    /// Rings the server's thread when a request arrives.
    pub doorbell: Arc<Doorbell>,
    /// Callers still connected: the server keeps answering until none is.
    pub clients: AtomicUsize,
    /// Cleared when the server's thread ends.
    pub open: AtomicBool,
}

impl<Req, Resp> Endpoint<Req, Resp> {
    pub fn new(doorbell: Arc<Doorbell>) -> Self {
        Self {
            requests: Mutex::new(VecDeque::new()),
            doorbell,
            clients: AtomicUsize::new(0),
            open: AtomicBool::new(true),
        }
    }

    pub fn take(&self) -> Option<PendingRequest<Req, Resp>> {
        self.requests.lock().unwrap_or_else(|e| e.into_inner()).pop_front()
    }
}

#[derive(Debug)]
struct LocalCaller<Req, Resp> {
    edge: String,
    endpoint: Arc<Endpoint<Req, Resp>>,
}

impl<Req, Resp> std::fmt::Debug for Endpoint<Req, Resp> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Endpoint").field("clients", &self.clients).finish()
    }
}

impl<Req: MessageHeader + Send, Resp: MessageHeader + Send> Call<Req, Resp> for LocalCaller<Req, Resp> {
    fn call(
        &mut self,
        header: Req,
        payload: &[f32],
        timeout: Duration,
        on_reply: &mut dyn FnMut(&Resp, &[f32]),
    ) -> Result<(), CallError> {
        if !self.endpoint.open.load(Ordering::SeqCst) {
            return Err(CallError::ServerGone { edge: self.edge.clone() });
        }
        let (reply, answer) = mpsc::sync_channel(1);
        let request = PendingRequest { header, payload: payload.to_vec(), reply };
        self.endpoint.requests.lock().unwrap_or_else(|e| e.into_inner()).push_back(request);
        self.endpoint.doorbell.ring();
        match answer.recv_timeout(timeout) {
            Ok((header, payload)) => {
                on_reply(&header, &payload);
                Ok(())
            }
            Err(mpsc::RecvTimeoutError::Timeout) => Err(CallError::Timeout { edge: self.edge.clone(), after: timeout }),
            // The server dropped the request unanswered: it has stopped.
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(CallError::ServerGone { edge: self.edge.clone() }),
        }
    }
}

impl<Req, Resp> Drop for LocalCaller<Req, Resp> {
    fn drop(&mut self) {
        self.endpoint.clients.fetch_sub(1, Ordering::SeqCst);
        self.endpoint.doorbell.ring();
    }
}

type Endpoints = Mutex<HashMap<String, Arc<dyn Any + Send + Sync>>>;

/// In-process servers by iceoryx2 service name (unique per graph instance).
fn endpoints() -> &'static Endpoints {
    static ENDPOINTS: OnceLock<Endpoints> = OnceLock::new();
    ENDPOINTS.get_or_init(Default::default)
}

pub(crate) fn open_endpoint<Req, Resp>(service: &str, endpoint: Arc<Endpoint<Req, Resp>>)
where
    Req: Send + 'static,
    Resp: Send + 'static,
{
    endpoints().lock().unwrap_or_else(|e| e.into_inner()).insert(service.to_string(), endpoint);
}

pub(crate) fn close_endpoint(service: &str) {
    endpoints().lock().unwrap_or_else(|e| e.into_inner()).remove(service);
}
