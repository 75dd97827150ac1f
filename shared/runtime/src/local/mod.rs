//! In-process mode: the same stage libraries as threads of one process,
//! connected by bounded queues instead of shared memory. A graph runs to
//! its end ([`LocalGraph::run`]), or is driven from outside
//! ([`LocalGraph::start`] with a [`Feed`] and a [`Collector`]): a
//! simulation or a planner hands it one message at a time and takes what
//! came out once the graph has settled.

mod driven;
pub(crate) mod queue;

pub use driven::{Collector, DriveError, Feed, RunningGraph};

use std::any::Any;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use poseflow_contracts::{Heartbeat, MessageHeader, StampSlot};

use crate::call::{Endpoint, PendingRequest, open_endpoint};
use crate::error::{BuildError, RuntimeError};
use crate::liveness::Liveness;
use crate::stage::{EmitError, Emitter, Flush, Input, Joined, Server, Sink, Source, SourceStep, Transform};
use queue::{Doorbell, InFlight, Queue, push_all};

/// How often a blocked stage looks at the stop flag.
const STOP_POLL: Duration = Duration::from_millis(50);

/// Why a stage cannot be added to a [`LocalGraph`].
#[derive(Debug, thiserror::Error)]
pub enum LocalGraphError {
    #[error("edge `{edge}` is not declared")]
    Undeclared { edge: String },
    #[error("edge `{edge}` carries another message type than {expected} expected by this stage")]
    MessageType { edge: String, expected: &'static str },
}

/// Overflow policy of a local edge (the graph file's `overflow`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LocalOverflow {
    DropOldest,
    Block,
}

/// The queues of one edge: one per reader.
#[derive(Debug)]
struct LocalEdge<H> {
    readers: Vec<Arc<Queue<H>>>,
}

/// Sends to every reader of an edge; detaches on drop, which ends the
/// stream once all publishers are gone.
struct LocalEmitter<'a, H> {
    readers: Vec<Arc<Queue<H>>>,
    slot: Option<StampSlot>,
    liveness: &'a Liveness,
    stop: &'a AtomicBool,
}

impl<H: MessageHeader> Emitter<H> for LocalEmitter<'_, H> {
    fn emit(&mut self, mut header: H, len: usize, fill: &mut dyn FnMut(&mut [f32])) -> Result<(), EmitError> {
        check_len(&header, len)?;
        if let Some(slot) = self.slot {
            header.header_mut().stamps.stamp(slot);
        }
        let mut payload = vec![0.0f32; len];
        fill(&mut payload);
        self.liveness.send_started();
        for queue in &self.readers {
            queue.wait_for_room(self.stop);
        }
        if !self.stop.load(Ordering::Relaxed) {
            push_all(&self.readers, (header, payload));
        }
        self.liveness.send_finished();
        self.liveness.count_sent();
        Ok(())
    }
}

impl<H> Drop for LocalEmitter<'_, H> {
    fn drop(&mut self) {
        for queue in &self.readers {
            queue.detach_publisher();
        }
    }
}

/// A stage's thread: builds the stage (on the thread that will own it:
/// iceoryx2 ports are not `Send`), then runs it.
type StageThread = Box<dyn FnOnce(Arc<AtomicBool>) -> StageEnd + Send>;
/// How a stage's thread ended: `Err` when the stage could not be built.
type StageEnd = Result<(), BuildError>;
type Edges = HashMap<String, Box<dyn Any + Send>>;
/// Builds a stage's thread once every reader of every edge is known.
type Deferred = Box<dyn FnOnce(&Edges) -> StageThread>;
/// Attaches a [`Feed`] to its edge's readers when the graph starts.
type AttachFeed = Box<dyn FnOnce(&Edges, &Arc<AtomicBool>)>;

/// A graph of stages as threads. Declare edges, add stages, then [`run`].
///
/// [`run`]: LocalGraph::run
pub struct LocalGraph {
    edges: Edges,
    specs: HashMap<String, (usize, LocalOverflow)>,
    pending: Vec<(String, Arc<Liveness>, Deferred)>,
    /// Request-response services served in-process, closed when the graph ends.
    services: Vec<String>,
    /// Publishers from outside the graph, attached when it starts.
    feeds: Vec<AttachFeed>,
    in_flight: Arc<InFlight>,
    /// Timestamp slots chosen by the graph, overriding the stage types'.
    stamp_slots: HashMap<String, Option<StampSlot>>,
}

impl std::fmt::Debug for LocalGraph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LocalGraph").field("stages", &self.pending.len()).finish()
    }
}

/// Final counters of every stage, keyed by stage name.
pub type LocalReport = BTreeMap<String, Heartbeat>;

impl Default for LocalGraph {
    fn default() -> Self {
        Self::new()
    }
}

impl LocalGraph {
    pub fn new() -> Self {
        Self {
            edges: HashMap::new(),
            specs: HashMap::new(),
            pending: Vec::new(),
            services: Vec::new(),
            feeds: Vec::new(),
            in_flight: Arc::new(InFlight::default()),
            stamp_slots: HashMap::new(),
        }
    }

    /// Makes stage `name`, added after this call, write `slot` on its
    /// outputs instead of its type's `SLOT` (the graph's `stamp` key).
    pub fn stamp_as(&mut self, name: &str, slot: Option<StampSlot>) {
        self.stamp_slots.insert(name.to_owned(), slot);
    }

    fn slot_of(&self, name: &str, default: Option<StampSlot>) -> Option<StampSlot> {
        self.stamp_slots.get(name).copied().unwrap_or(default)
    }

    /// Declares an edge's queue size and overflow policy.
    pub fn edge(&mut self, name: &str, queue: usize, overflow: LocalOverflow) {
        self.specs.insert(name.to_string(), (queue.max(1), overflow));
    }

    fn typed<H: MessageHeader + Send + 'static>(&mut self, name: &str) -> Result<&mut LocalEdge<H>, LocalGraphError> {
        if !self.edges.contains_key(name) {
            self.edges.insert(name.to_string(), Box::new(LocalEdge::<H> { readers: Vec::new() }));
        }
        self.edges[name]
            .is::<LocalEdge<H>>()
            .then_some(())
            .ok_or_else(|| LocalGraphError::MessageType { edge: name.to_string(), expected: H::NAME })?;
        Ok(self.edges.get_mut(name).and_then(|e| e.downcast_mut::<LocalEdge<H>>()).expect("checked above"))
    }

    fn subscribe<H: MessageHeader + Send + 'static>(&mut self, name: &str) -> Result<Arc<Queue<H>>, LocalGraphError> {
        self.subscribe_ringing(name, None)
    }

    /// Subscribes with a queue that also rings `doorbell` on every push.
    fn subscribe_ringing<H: MessageHeader + Send + 'static>(
        &mut self,
        name: &str,
        doorbell: Option<Arc<Doorbell>>,
    ) -> Result<Arc<Queue<H>>, LocalGraphError> {
        let (capacity, overflow) =
            *self.specs.get(name).ok_or_else(|| LocalGraphError::Undeclared { edge: name.to_string() })?;
        let queue = Arc::new(Queue::new(capacity, overflow, doorbell, Some(self.in_flight.clone())));
        self.typed::<H>(name)?.readers.push(queue.clone());
        Ok(queue)
    }

    /// The readers of an edge, as known when [`run`](Self::run) starts.
    fn publish<H: MessageHeader + Send + 'static>(
        &mut self,
        name: &str,
    ) -> Result<PendingPublisher<H>, LocalGraphError> {
        self.typed::<H>(name)?;
        Ok(PendingPublisher { edge: name.to_string(), _marker: std::marker::PhantomData })
    }

    fn readers_of<H: MessageHeader + Send + 'static>(edges: &Edges, name: &str) -> Vec<Arc<Queue<H>>> {
        let readers = edges
            .get(name)
            .and_then(|e| e.downcast_ref::<LocalEdge<H>>())
            .map(|e| e.readers.clone())
            .unwrap_or_default();
        for queue in &readers {
            queue.attach_publisher();
        }
        readers
    }

    pub fn add_source<S: Source + 'static>(
        &mut self,
        name: &str,
        make: impl FnOnce() -> Result<S, BuildError> + Send + 'static,
        output: &str,
        rate_hz: Option<f64>,
    ) -> Result<(), LocalGraphError>
    where
        S::Out: Send + 'static,
    {
        let pending = self.publish::<S::Out>(output)?;
        let slot = self.slot_of(name, S::SLOT);
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<S::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut source = build_or_stop(make, &stop, &live)?;
                let mut emitter = LocalEmitter { readers, slot, liveness: &live, stop: &stop };
                let period = rate_hz.filter(|hz| *hz > 0.0).map(|hz| Duration::from_secs_f64(1.0 / hz));
                let mut next = Instant::now();
                while !stop.load(Ordering::Relaxed) {
                    if let Some(period) = period {
                        // Pacing a synthetic source; not on any data path.
                        std::thread::sleep(next.saturating_duration_since(Instant::now()));
                        next += period;
                    }
                    let started = Instant::now();
                    live.work_started();
                    let step = source.next(&mut emitter);
                    live.source_step_finished(step.as_ref().ok().copied(), started.elapsed());
                    live.count_errors(source.take_rejected());
                    match step {
                        Ok(SourceStep::Continue | SourceStep::Idle) => {}
                        Ok(SourceStep::Finished) => break,
                        Err(err) => {
                            live.count_error();
                            tracing::warn!(err = %crate::error_chain(&err), "source failed; frame skipped");
                        }
                    }
                }
                Ok(())
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    pub fn add_transform<T: Transform + 'static>(
        &mut self,
        name: &str,
        make: impl FnOnce() -> Result<T, BuildError> + Send + 'static,
        input: &str,
        output: &str,
    ) -> Result<(), LocalGraphError>
    where
        T::In: Send + 'static,
        T::Out: Send + 'static,
    {
        let queue = self.subscribe::<T::In>(input)?;
        let pending = self.publish::<T::Out>(output)?;
        let slot = self.slot_of(name, T::SLOT);
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<T::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut stage = build_or_stop(make, &stop, &live)?;
                let mut emitter = LocalEmitter { readers, slot, liveness: &live, stop: &stop };
                // Inputs processed since the stage last ran empty: handled
                // once the flush has queued their outputs.
                let mut unflushed = 0;
                loop {
                    let next = queue.try_pop().or_else(|| {
                        if unflushed > 0 {
                            live.flush(&mut stage, &mut emitter, Flush::Idle);
                            queue.handled_many(std::mem::take(&mut unflushed));
                        }
                        queue.pop(&stop)
                    });
                    let Some((header, payload)) = next else { break };
                    transform_one(&mut stage, &header, &payload, &mut emitter, &live);
                    unflushed += 1;
                }
                live.flush(&mut stage, &mut emitter, Flush::End);
                queue.handled_many(unflushed);
                queue.close();
                Ok(())
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    /// Adds a [`Joined`] stage: `side` messages are handed to it before
    /// each input, so every side message published before an input is seen
    /// before that input (a message reaches all readers of its edge at
    /// once, see [`push_all`]).
    pub fn add_joined<J: Joined + 'static>(
        &mut self,
        name: &str,
        make: impl FnOnce() -> Result<J, BuildError> + Send + 'static,
        input: &str,
        side: &str,
        output: &str,
    ) -> Result<(), LocalGraphError>
    where
        J::In: Send + 'static,
        J::Side: Send + 'static,
        J::Out: Send + 'static,
    {
        let doorbell = Arc::new(Doorbell::default());
        let queue = self.subscribe_ringing::<J::In>(input, Some(doorbell.clone()))?;
        let side_queue = self.subscribe_ringing::<J::Side>(side, Some(doorbell.clone()))?;
        let pending = self.publish::<J::Out>(output)?;
        let slot = self.slot_of(name, J::SLOT);
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<J::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut stage = build_or_stop(make, &stop, &live)?;
                let read_side = |stage: &mut J| {
                    while let Some((header, payload)) = side_queue.try_pop() {
                        if let Err(err) = stage.side(Input { header: &header, payload: &payload }) {
                            live.count_error();
                            tracing::warn!(err = %crate::error_chain(&err), "side input failed; message skipped");
                        }
                        side_queue.handled();
                    }
                };
                // Outputs are held until the stage has returned, then
                // delivered while side messages keep being read: in a loop
                // the side input's writer may be this output's reader, itself
                // waiting for room on the side input.
                let mut held = HeldOutputs { messages: Vec::new(), slot };
                let deliver_held = |held: &mut HeldOutputs<J::Out>, stage: &mut J| {
                    for message in held.messages.drain(..) {
                        deliver(message, &readers, &live, &stop, &mut || read_side(stage));
                    }
                };
                let mut unflushed = 0;
                while !stop.load(Ordering::Relaxed) {
                    let seen = doorbell.count();
                    read_side(&mut stage);
                    if let Some((header, payload)) = queue.try_pop() {
                        crate::stage::await_side(&mut stage, &header, read_side);
                        transform_one(&mut stage, &header, &payload, &mut held, &live);
                        deliver_held(&mut held, &mut stage);
                        unflushed += 1;
                        continue;
                    }
                    if unflushed > 0 {
                        live.flush(&mut stage, &mut held, Flush::Idle);
                        deliver_held(&mut held, &mut stage);
                        queue.handled_many(std::mem::take(&mut unflushed));
                        // Side messages may have come meanwhile.
                        continue;
                    }
                    if queue.ended() {
                        break;
                    }
                    doorbell.wait_past(seen, STOP_POLL);
                }
                live.flush(&mut stage, &mut held, Flush::End);
                deliver_held(&mut held, &mut stage);
                queue.handled_many(unflushed);
                // The end of the output stream (as an emitter's drop does).
                for reader in &readers {
                    reader.detach_publisher();
                }
                queue.close();
                side_queue.close();
                Ok(())
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    /// Adds a [`Server`]: a transform that also answers the requests of the
    /// in-process callers of `service` (see [`crate::call::connect`]). It
    /// answers requests before taking the next input, keeps answering while
    /// its output is full (its caller may be the reader it waits for), and
    /// after its input has ended until every caller has gone.
    pub fn add_server<S: Server + 'static>(
        &mut self,
        name: &str,
        make: impl FnOnce() -> Result<S, BuildError> + Send + 'static,
        input: &str,
        service: &str,
        output: &str,
    ) -> Result<(), LocalGraphError>
    where
        S::In: Send + 'static,
        S::Out: Send + 'static,
        S::Request: Send + 'static,
        S::Response: Send + 'static,
    {
        let doorbell = Arc::new(Doorbell::default());
        let endpoint = Arc::new(Endpoint::<S::Request, S::Response>::new(doorbell.clone()));
        open_endpoint(service, endpoint.clone());
        self.services.push(service.to_string());
        let queue = self.subscribe_ringing::<S::In>(input, Some(doorbell.clone()))?;
        let pending = self.publish::<S::Out>(output)?;
        let slot = self.slot_of(name, S::SLOT);
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<S::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut stage = build_or_stop(make, &stop, &live)?;
                let answer_all = |stage: &mut S| {
                    while let Some(request) = endpoint.take() {
                        answer(stage, request, slot, &live);
                    }
                };
                let mut held = HeldOutputs { messages: Vec::new(), slot };
                let mut unflushed = 0;
                while !stop.load(Ordering::Relaxed) {
                    let seen = doorbell.count();
                    answer_all(&mut stage);
                    let Some((header, payload)) = queue.try_pop() else {
                        if unflushed > 0 {
                            live.flush(&mut stage, &mut held, Flush::Idle);
                            for message in held.messages.drain(..) {
                                deliver(message, &readers, &live, &stop, &mut || answer_all(&mut stage));
                            }
                            queue.handled_many(std::mem::take(&mut unflushed));
                            continue;
                        }
                        if queue.ended() {
                            break;
                        }
                        doorbell.wait_past(seen, STOP_POLL);
                        continue;
                    };
                    transform_one(&mut stage, &header, &payload, &mut held, &live);
                    for message in held.messages.drain(..) {
                        deliver(message, &readers, &live, &stop, &mut || answer_all(&mut stage));
                    }
                    unflushed += 1;
                }
                live.flush(&mut stage, &mut held, Flush::End);
                for message in held.messages.drain(..) {
                    deliver(message, &readers, &live, &stop, &mut || answer_all(&mut stage));
                }
                queue.handled_many(unflushed);
                queue.close();
                // The end of the output stream reaches the callers, which may
                // still ask about the conditions they hold.
                for reader in &readers {
                    reader.detach_publisher();
                }
                while !stop.load(Ordering::Relaxed) && endpoint.clients.load(Ordering::SeqCst) > 0 {
                    let seen = doorbell.count();
                    answer_all(&mut stage);
                    doorbell.wait_past(seen, STOP_POLL);
                }
                endpoint.open.store(false, Ordering::SeqCst);
                answer_all(&mut stage);
                Ok(())
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    pub fn add_sink<K: Sink + 'static>(
        &mut self,
        name: &str,
        make: impl FnOnce() -> Result<K, BuildError> + Send + 'static,
        input: &str,
    ) -> Result<(), LocalGraphError>
    where
        K::In: Send + 'static,
    {
        let queue = self.subscribe::<K::In>(input)?;
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |_| {
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut sink = build_or_stop(make, &stop, &live)?;
                while let Some((header, payload)) = queue.pop(&stop) {
                    live.count_received(header.header().frame_id);
                    let started = Instant::now();
                    live.work_started();
                    if let Err(err) = sink.consume(Input { header: &header, payload: &payload }) {
                        live.count_error();
                        tracing::warn!(err = %crate::error_chain(&err), "consume failed; frame skipped");
                    }
                    live.work_finished(started.elapsed());
                    queue.handled();
                }
                queue.close();
                if let Err(err) = sink.finish() {
                    tracing::error!(err = %crate::error_chain(&err), "sink could not finish");
                }
                Ok(())
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    /// A publisher of `edge` from outside the graph: what it sends reaches
    /// the edge's readers as a stage's output would. Dropping it ends the
    /// edge's stream (when it is the edge's only publisher).
    pub fn feed<H: MessageHeader + Send + 'static>(&mut self, edge: &str) -> Result<Feed<H>, LocalGraphError> {
        let pending = self.publish::<H>(edge)?;
        let feed = Feed::new(edge);
        let attach = feed.attachment();
        self.feeds.push(Box::new(move |edges, stop| {
            attach(Self::readers_of::<H>(edges, &pending.edge), stop.clone());
        }));
        Ok(feed)
    }

    /// A reader of `edge` outside the graph: it keeps every message (it is
    /// unbounded, so it never holds the graph back) until drained.
    pub fn collect<H: MessageHeader + Send + 'static>(&mut self, edge: &str) -> Result<Collector<H>, LocalGraphError> {
        if !self.specs.contains_key(edge) {
            return Err(LocalGraphError::Undeclared { edge: edge.to_string() });
        }
        let queue = Arc::new(Queue::new(usize::MAX, LocalOverflow::Block, None, None));
        self.typed::<H>(edge)?.readers.push(queue.clone());
        Ok(Collector::new(queue))
    }

    fn defer(&mut self, name: &str, liveness: Arc<Liveness>, run: Deferred) {
        self.pending.push((name.to_string(), liveness, run));
    }

    /// Runs every stage in its own thread until all have finished (the
    /// sources ended and everything drained) or `stop` is set. Every
    /// [`Feed`] must have been dropped, or the graph never ends.
    pub fn run(self, stop: Arc<AtomicBool>) -> Result<LocalReport, RuntimeError> {
        self.start(stop).finish()
    }

    /// Starts every stage in its own thread and returns at once: the graph
    /// is then driven through its feeds and collectors.
    pub fn start(self, stop: Arc<AtomicBool>) -> RunningGraph {
        // Every publisher attaches to its readers before any thread starts,
        // so no reader mistakes "not started yet" for "finished".
        for feed in self.feeds {
            feed(&self.edges, &stop);
        }
        let threads: Vec<(String, Arc<Liveness>, StageThread)> =
            self.pending.into_iter().map(|(name, live, deferred)| (name, live, deferred(&self.edges))).collect();
        let stages = threads
            .into_iter()
            .map(|(name, live, thread)| {
                let stop = stop.clone();
                let span = tracing::info_span!("stage", name = %name);
                let handle = std::thread::Builder::new()
                    .name(name.clone())
                    .spawn(move || span.in_scope(|| thread(stop)))
                    .expect("spawn a stage thread");
                (name, live, handle)
            })
            .collect();
        RunningGraph::new(stages, self.services, stop, self.in_flight)
    }
}

struct PendingPublisher<H> {
    edge: String,
    _marker: std::marker::PhantomData<fn() -> H>,
}

/// A server's outputs of one input, held until it has returned.
struct HeldOutputs<H> {
    messages: Vec<(H, Vec<f32>)>,
    slot: Option<StampSlot>,
}

impl<H: MessageHeader> Emitter<H> for HeldOutputs<H> {
    fn emit(&mut self, mut header: H, len: usize, fill: &mut dyn FnMut(&mut [f32])) -> Result<(), EmitError> {
        check_len(&header, len)?;
        if let Some(slot) = self.slot {
            header.header_mut().stamps.stamp(slot);
        }
        let mut payload = vec![0.0f32; len];
        fill(&mut payload);
        self.messages.push((header, payload));
        Ok(())
    }
}

fn check_len<H: MessageHeader>(header: &H, len: usize) -> Result<(), EmitError> {
    let expected = header.payload_len().map_err(|source| EmitError::Header { message: H::NAME, source })?;
    if expected != len {
        return Err(EmitError::Length { message: H::NAME, len, expected });
    }
    Ok(())
}

/// Queues `message` for every reader, calling `meanwhile` while a blocking
/// queue is full.
fn deliver<H: Clone>(
    message: (H, Vec<f32>),
    readers: &[Arc<Queue<H>>],
    liveness: &Liveness,
    stop: &AtomicBool,
    meanwhile: &mut dyn FnMut(),
) {
    /// How long a server waits for room before answering requests again.
    const FULL_RETRY: Duration = Duration::from_micros(200);
    liveness.send_started();
    while !readers.iter().all(|q| q.has_room()) {
        if stop.load(Ordering::Relaxed) {
            liveness.send_finished();
            return;
        }
        meanwhile();
        std::thread::sleep(FULL_RETRY);
    }
    push_all(readers, message);
    liveness.send_finished();
    liveness.count_sent();
}

/// Answers one in-process request (an invalid one with an error status).
fn answer<S: Server>(
    stage: &mut S,
    request: PendingRequest<S::Request, S::Response>,
    slot: Option<StampSlot>,
    liveness: &Liveness,
) {
    let started = Instant::now();
    liveness.work_started();
    let mut reply = HeldOutputs { messages: Vec::new(), slot };
    let answered = match request.header.check_payload(&request.payload) {
        Ok(()) => stage.answer(Input { header: &request.header, payload: &request.payload }, &mut reply),
        Err(err) => {
            liveness.count_error();
            tracing::warn!(err = %crate::error_chain(&err), "request breaks its contract; answered as invalid");
            stage.answer_invalid(&request.header, &mut reply)
        }
    };
    liveness.work_finished(started.elapsed());
    liveness.count_errors(stage.take_rejected());
    if let Err(err) = answered {
        liveness.count_error();
        tracing::warn!(err = %crate::error_chain(&err), "request not answered");
    }
    if let Some(response) = reply.messages.pop() {
        // The caller may have timed out and gone: nothing to do then.
        let _ = request.reply.send(response);
    }
}

/// Builds a stage on its thread; a failure stops the whole graph.
fn build_or_stop<T>(
    make: impl FnOnce() -> Result<T, BuildError>,
    stop: &AtomicBool,
    live: &Liveness,
) -> Result<T, BuildError> {
    let stage = make().inspect_err(|_| stop.store(true, Ordering::Relaxed))?;
    live.mark_built();
    Ok(stage)
}

/// Hands one input to a transform, timing and counting it as a process does.
fn transform_one<T: Transform>(
    stage: &mut T,
    header: &T::In,
    payload: &[f32],
    output: &mut dyn Emitter<T::Out>,
    live: &Liveness,
) {
    live.count_received(header.header().frame_id);
    let started = Instant::now();
    live.work_started();
    if let Err(err) = stage.process(Input { header, payload }, output) {
        live.count_error();
        tracing::warn!(err = %crate::error_chain(&err), "process failed; frame skipped");
    }
    live.count_errors(stage.take_rejected());
    live.work_finished(started.elapsed());
}

#[cfg(test)]
mod tests;
