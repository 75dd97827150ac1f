//! In-process mode: the same stage libraries as threads of one process,
//! connected by bounded queues instead of shared memory. It is the
//! baseline of the latency benchmarks and a convenient harness for tests.

use std::any::Any;
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use poseflow_contracts::{Heartbeat, MessageHeader, Stage, StageState};

use crate::call::{Endpoint, PendingRequest, close_endpoint, open_endpoint};
use crate::error::{BuildError, RuntimeError};
use crate::liveness::Liveness;
use crate::stage::{EmitError, Emitter, Input, Joined, Server, Sink, Source, SourceStep, Transform};

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

/// Wakes a stage that waits on more than one thing (its input and side
/// inputs, or its input and its requests): every push rings it.
#[derive(Debug, Default)]
pub(crate) struct Doorbell {
    rung: Mutex<u64>,
    changed: Condvar,
}

impl Doorbell {
    pub fn ring(&self) {
        *self.rung.lock().unwrap_or_else(|e| e.into_inner()) += 1;
        self.changed.notify_all();
    }

    pub fn count(&self) -> u64 {
        *self.rung.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Sleeps until it rings after `seen` was read, or `timeout` passes.
    pub fn wait_past(&self, seen: u64, timeout: Duration) {
        let rung = self.rung.lock().unwrap_or_else(|e| e.into_inner());
        if *rung == seen {
            let _ = self.changed.wait_timeout(rung, timeout);
        }
    }
}

/// Queues `message` for every reader at once (all their locks held), so a
/// stage reading two of them (an input and a side input) never sees the
/// message on one before the other. A full blocking queue is waited for
/// before (see [`Queue::wait_for_room`]); a full drop-oldest one loses its
/// oldest message; a closed one drops it.
fn push_all<H: Clone>(readers: &[Arc<Queue<H>>], message: (H, Vec<f32>)) {
    let mut states: Vec<_> = readers.iter().map(|q| q.state.lock().unwrap_or_else(|e| e.into_inner())).collect();
    let mut open: Vec<(&Arc<Queue<H>>, &mut QueueState<H>)> =
        readers.iter().zip(states.iter_mut().map(|state| &mut **state)).filter(|(_, state)| !state.closed).collect();
    if let Some((last, others)) = open.split_last_mut() {
        for (queue, state) in others.iter_mut() {
            enqueue(queue, state, message.clone());
        }
        // The last reader takes the message itself: a Frame is megabytes.
        enqueue(last.0, last.1, message);
    }
    drop(states);
    for queue in readers {
        queue.ring();
    }
}

/// Appends to a locked, open queue; a full one loses its oldest message
/// (a blocking one was waited for before it was locked).
fn enqueue<H>(queue: &Queue<H>, state: &mut QueueState<H>, message: (H, Vec<f32>)) {
    if state.messages.len() >= queue.capacity {
        state.messages.pop_front();
    }
    state.messages.push_back(message);
}

/// One reader's bounded queue.
#[derive(Debug)]
struct Queue<H> {
    state: Mutex<QueueState<H>>,
    changed: Condvar,
    capacity: usize,
    overflow: LocalOverflow,
    doorbell: Option<Arc<Doorbell>>,
}

#[derive(Debug)]
struct QueueState<H> {
    messages: VecDeque<(H, Vec<f32>)>,
    /// Publishers still attached; the stream ends when it reaches 0.
    publishers: usize,
    /// The reader has ended: later messages are dropped, not queued, so no
    /// publisher waits for room that never comes.
    closed: bool,
}

impl<H> Queue<H> {
    fn ring(&self) {
        self.changed.notify_all();
        if let Some(doorbell) = &self.doorbell {
            doorbell.ring();
        }
    }

    /// Whether a message can be queued now without waiting.
    fn has_room(&self) -> bool {
        let state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.closed || self.overflow == LocalOverflow::DropOldest || state.messages.len() < self.capacity
    }

    /// Waits until [`Self::has_room`] or `stop`. Only the edge's one
    /// publisher queues here, so the room is still there when it pushes.
    fn wait_for_room(&self, stop: &AtomicBool) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        while self.overflow == LocalOverflow::Block
            && state.messages.len() >= self.capacity
            && !state.closed
            && !stop.load(Ordering::Relaxed)
        {
            state = self.changed.wait_timeout(state, STOP_POLL).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    fn try_pop(&self) -> Option<(H, Vec<f32>)> {
        let message = self.state.lock().unwrap_or_else(|e| e.into_inner()).messages.pop_front();
        if message.is_some() {
            self.changed.notify_all();
        }
        message
    }

    /// Every publisher is gone and the queue is drained.
    fn ended(&self) -> bool {
        let state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.publishers == 0 && state.messages.is_empty()
    }

    fn close(&self) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.closed = true;
        state.messages.clear();
        drop(state);
        self.changed.notify_all();
    }

    /// The next message; `None` once every publisher is gone and the queue
    /// is drained, or when `stop` is set.
    fn pop(&self, stop: &AtomicBool) -> Option<(H, Vec<f32>)> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if let Some(message) = state.messages.pop_front() {
                self.changed.notify_all();
                return Some(message);
            }
            if state.publishers == 0 || stop.load(Ordering::Relaxed) {
                return None;
            }
            state = self.changed.wait_timeout(state, STOP_POLL).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    fn detach_publisher(&self) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.publishers -= 1;
        drop(state);
        self.ring();
    }
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
    slot: Option<Stage>,
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

/// A graph of stages as threads. Declare edges, add stages, then [`run`].
///
/// [`run`]: LocalGraph::run
pub struct LocalGraph {
    edges: Edges,
    specs: HashMap<String, (usize, LocalOverflow)>,
    pending: Vec<(String, Arc<Liveness>, Deferred)>,
    /// Request-response services served in-process, closed when the graph ends.
    services: Vec<String>,
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
        Self { edges: HashMap::new(), specs: HashMap::new(), pending: Vec::new(), services: Vec::new() }
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
        let queue = Arc::new(Queue {
            state: Mutex::new(QueueState { messages: VecDeque::new(), publishers: 0, closed: false }),
            changed: Condvar::new(),
            capacity,
            overflow,
            doorbell,
        });
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
            queue.state.lock().unwrap_or_else(|e| e.into_inner()).publishers += 1;
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
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<S::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut source = build_or_stop(make, &stop)?;
                let mut emitter = LocalEmitter { readers, slot: S::SLOT, liveness: &live, stop: &stop };
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
                    live.work_finished(started.elapsed());
                    live.count_errors(source.take_rejected());
                    match step {
                        Ok(SourceStep::Continue) => {}
                        Ok(SourceStep::Finished) => break,
                        Err(err) => {
                            live.count_error();
                            tracing::warn!(%err, "source failed; frame skipped");
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
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<T::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut stage = build_or_stop(make, &stop)?;
                let mut emitter = LocalEmitter { readers, slot: T::SLOT, liveness: &live, stop: &stop };
                while let Some((header, payload)) = queue.pop(&stop) {
                    transform_one(&mut stage, &header, &payload, &mut emitter, &live);
                }
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
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<J::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut stage = build_or_stop(make, &stop)?;
                let mut emitter = LocalEmitter { readers, slot: J::SLOT, liveness: &live, stop: &stop };
                while !stop.load(Ordering::Relaxed) {
                    let seen = doorbell.count();
                    while let Some((header, payload)) = side_queue.try_pop() {
                        if let Err(err) = stage.side(Input { header: &header, payload: &payload }) {
                            live.count_error();
                            tracing::warn!(%err, "side input failed; message skipped");
                        }
                    }
                    if let Some((header, payload)) = queue.try_pop() {
                        transform_one(&mut stage, &header, &payload, &mut emitter, &live);
                        continue;
                    }
                    if queue.ended() {
                        break;
                    }
                    doorbell.wait_past(seen, STOP_POLL);
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
        let liveness = Arc::new(Liveness::new());
        let live = liveness.clone();
        let run: Deferred = Box::new(move |edges| {
            let readers = Self::readers_of::<S::Out>(edges, &pending.edge);
            Box::new(move |stop: Arc<AtomicBool>| {
                let mut stage = build_or_stop(make, &stop)?;
                let answer_all = |stage: &mut S| {
                    while let Some(request) = endpoint.take() {
                        answer(stage, request, &live);
                    }
                };
                let mut held = HeldOutputs { messages: Vec::new(), slot: S::SLOT };
                while !stop.load(Ordering::Relaxed) {
                    let seen = doorbell.count();
                    answer_all(&mut stage);
                    let Some((header, payload)) = queue.try_pop() else {
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
                }
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
                let mut sink = build_or_stop(make, &stop)?;
                while let Some((header, payload)) = queue.pop(&stop) {
                    live.count_received(header.header().frame_id);
                    let started = Instant::now();
                    live.work_started();
                    if let Err(err) = sink.consume(Input { header: &header, payload: &payload }) {
                        live.count_error();
                        tracing::warn!(%err, "consume failed; frame skipped");
                    }
                    live.work_finished(started.elapsed());
                }
                queue.close();
                if let Err(err) = sink.finish() {
                    tracing::error!(%err, "sink could not finish");
                }
                Ok(())
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    fn defer(&mut self, name: &str, liveness: Arc<Liveness>, run: Deferred) {
        self.pending.push((name.to_string(), liveness, run));
    }

    /// Runs every stage in its own thread until all have finished (the
    /// sources ended and everything drained) or `stop` is set.
    pub fn run(self, stop: Arc<AtomicBool>) -> Result<LocalReport, RuntimeError> {
        // Every publisher attaches to its readers before any thread starts,
        // so no reader mistakes "not started yet" for "finished".
        let threads: Vec<(String, Arc<Liveness>, StageThread)> =
            self.pending.into_iter().map(|(name, live, deferred)| (name, live, deferred(&self.edges))).collect();
        let handles: Vec<(String, Arc<Liveness>, JoinHandle<StageEnd>)> = threads
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
        let mut failure = None;
        let mut report = LocalReport::new();
        for (name, live, handle) in handles {
            match handle.join() {
                Ok(Ok(())) => {}
                Ok(Err(source)) => {
                    live.count_error();
                    failure.get_or_insert(RuntimeError::Build { stage: name.clone(), source });
                }
                Err(_) => {
                    live.count_error();
                    tracing::error!(stage = %name, "stage thread panicked");
                }
            }
            live.set_state(StageState::Finished);
            report.insert(name, live.heartbeat());
        }
        for service in &self.services {
            close_endpoint(service);
        }
        match failure {
            Some(err) => Err(err),
            None => Ok(report),
        }
    }
}

struct PendingPublisher<H> {
    edge: String,
    _marker: std::marker::PhantomData<fn() -> H>,
}

/// A server's outputs of one input, held until it has returned.
struct HeldOutputs<H> {
    messages: Vec<(H, Vec<f32>)>,
    slot: Option<Stage>,
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
    let expected = header.payload_len().map_err(|e| EmitError(e.to_string()))?;
    if expected != len {
        return Err(EmitError(format!("{}: payload of {len} values, the header announces {expected}", H::NAME)));
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
fn answer<S: Server>(stage: &mut S, request: PendingRequest<S::Request, S::Response>, liveness: &Liveness) {
    let started = Instant::now();
    liveness.work_started();
    let mut reply = HeldOutputs { messages: Vec::new(), slot: S::SLOT };
    let answered = match request.header.check_payload(&request.payload) {
        Ok(()) => stage.answer(Input { header: &request.header, payload: &request.payload }, &mut reply),
        Err(err) => {
            liveness.count_error();
            tracing::warn!(%err, "request breaks its contract; answered as invalid");
            stage.answer_invalid(&request.header, &mut reply)
        }
    };
    liveness.work_finished(started.elapsed());
    liveness.count_errors(stage.take_rejected());
    if let Err(err) = answered {
        liveness.count_error();
        tracing::warn!(%err, "request not answered");
    }
    if let Some(response) = reply.messages.pop() {
        // The caller may have timed out and gone: nothing to do then.
        let _ = request.reply.send(response);
    }
}

/// Builds a stage on its thread; a failure stops the whole graph.
fn build_or_stop<T>(make: impl FnOnce() -> Result<T, BuildError>, stop: &AtomicBool) -> Result<T, BuildError> {
    make().inspect_err(|_| stop.store(true, Ordering::Relaxed))
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
        tracing::warn!(%err, "process failed; frame skipped");
    }
    live.count_errors(stage.take_rejected());
    live.work_finished(started.elapsed());
}

#[cfg(test)]
mod tests {
    use std::sync::{Arc, Mutex};

    use poseflow_contracts::{
        Header, HypothesesHeader, POSE_LEN, VELOCITY_LEN, VelocityRequest, VelocityResponse, status,
    };
    use poseflow_graph::{EdgeWiring, OverflowPolicy};

    use super::*;
    use crate::call::{Call, connect};

    #[derive(Debug, thiserror::Error)]
    #[error("{0}")]
    struct TestError(String);

    impl From<EmitError> for TestError {
        fn from(err: EmitError) -> Self {
            TestError(err.to_string())
        }
    }

    fn hypotheses(frame: u64) -> HypothesesHeader {
        HypothesesHeader { header: Header::new(frame, 1), sample_count: 1, step_count: 1 }
    }

    /// Frames 0..n, one pose each, every value the frame number.
    struct Counter(u64, u64);

    impl Source for Counter {
        type Out = HypothesesHeader;
        type Error = TestError;
        const SLOT: Option<Stage> = None;

        fn next(&mut self, output: &mut dyn Emitter<HypothesesHeader>) -> Result<SourceStep, TestError> {
            if self.0 == self.1 {
                return Ok(SourceStep::Finished);
            }
            let frame = self.0;
            self.0 += 1;
            output.emit(hypotheses(frame), POSE_LEN, &mut |out| out.fill(frame as f32))?;
            Ok(SourceStep::Continue)
        }
    }

    /// Passes its input on and answers each velocity request with twice the
    /// request's first value.
    struct Doubler;

    impl Transform for Doubler {
        type In = HypothesesHeader;
        type Out = HypothesesHeader;
        type Error = TestError;
        const SLOT: Option<Stage> = None;

        fn process(
            &mut self,
            input: Input<'_, HypothesesHeader>,
            output: &mut dyn Emitter<HypothesesHeader>,
        ) -> Result<(), TestError> {
            Ok(output.emit(*input.header, input.payload.len(), &mut |out| out.copy_from_slice(input.payload))?)
        }
    }

    impl Server for Doubler {
        type Request = VelocityRequest;
        type Response = VelocityResponse;

        fn answer(
            &mut self,
            request: Input<'_, VelocityRequest>,
            reply: &mut dyn Emitter<VelocityResponse>,
        ) -> Result<(), TestError> {
            let header = VelocityResponse {
                header: request.header.header,
                request_id: request.header.request_id,
                sample_count: 1,
                status: status::OK,
            };
            let doubled = 2.0 * request.payload[0];
            Ok(reply.emit(header, VELOCITY_LEN, &mut |out| out.fill(doubled))?)
        }

        fn answer_invalid(
            &mut self,
            _request: &VelocityRequest,
            _reply: &mut dyn Emitter<VelocityResponse>,
        ) -> Result<(), TestError> {
            Err(TestError("invalid request".into()))
        }
    }

    /// Asks the server about each input; outputs the answer. Also a joined
    /// stage: it notes whether each input's frame came by the side input
    /// first.
    struct Asker {
        client: Box<dyn Call<VelocityRequest, VelocityResponse>>,
        seen_on_side: Vec<u64>,
        side_first: Arc<Mutex<Vec<bool>>>,
    }

    impl Transform for Asker {
        type In = HypothesesHeader;
        type Out = HypothesesHeader;
        type Error = TestError;
        const SLOT: Option<Stage> = None;

        fn process(
            &mut self,
            input: Input<'_, HypothesesHeader>,
            output: &mut dyn Emitter<HypothesesHeader>,
        ) -> Result<(), TestError> {
            let frame = input.header.header.frame_id;
            self.side_first.lock().unwrap().push(self.seen_on_side.contains(&frame));
            let request = VelocityRequest {
                header: input.header.header,
                condition_id: 0,
                request_id: frame,
                sample_count: 1,
                t: 0.5,
                step_index: 0,
                step_count: 1,
            };
            let mut answer = None;
            self.client
                .call(request, input.payload, Duration::from_secs(5), &mut |_, payload| answer = Some(payload[0]))
                .map_err(|e| TestError(e.to_string()))?;
            let answer = answer.ok_or_else(|| TestError("no answer".into()))?;
            Ok(output.emit(*input.header, POSE_LEN, &mut |out| out.fill(answer))?)
        }
    }

    impl Joined for Asker {
        type Side = HypothesesHeader;

        fn side(&mut self, input: Input<'_, HypothesesHeader>) -> Result<(), TestError> {
            self.seen_on_side.push(input.header.header.frame_id);
            Ok(())
        }
    }

    struct Collect(Arc<Mutex<Vec<f32>>>);

    impl Sink for Collect {
        type In = HypothesesHeader;
        type Error = TestError;

        fn consume(&mut self, input: Input<'_, HypothesesHeader>) -> Result<(), TestError> {
            self.0.lock().unwrap().push(input.payload[0]);
            Ok(())
        }

        fn finish(&mut self) -> Result<(), TestError> {
            Ok(())
        }
    }

    fn velocities_edge(service: &str) -> EdgeWiring {
        EdgeWiring {
            edge: "velocities".into(),
            service: service.into(),
            message: "Velocity".into(),
            queue: 1,
            overflow: OverflowPolicy::Block,
            max_payload_len: 64,
            readers: 1,
        }
    }

    /// counter → doubler (serving velocities) → asker (calling it; the
    /// counter's output as its side input) → collect, with one-slot
    /// blocking queues: every frame arrives doubled and in order, each
    /// input's side message was handed over before it, and the server
    /// answers while its own output is full.
    #[test]
    fn a_server_answers_its_in_process_caller_and_side_inputs_come_first() {
        const FRAMES: u64 = 200;
        let service = "poseflow/local-test/velocities";
        let mut local = LocalGraph::new();
        for edge in ["raw", "passed", "asked"] {
            local.edge(edge, 1, LocalOverflow::Block);
        }
        let collected = Arc::new(Mutex::new(Vec::new()));
        let side_first = Arc::new(Mutex::new(Vec::new()));
        local.add_source("counter", || Ok(Counter(0, FRAMES)), "raw", None).unwrap();
        local.add_server("doubler", || Ok(Doubler), "raw", service, "passed").unwrap();
        let side = side_first.clone();
        let make_asker = move || -> Result<Asker, BuildError> {
            let client = connect("asker", &velocities_edge(service))?;
            Ok(Asker { client, seen_on_side: Vec::new(), side_first: side })
        };
        local.add_joined("asker", make_asker, "passed", "raw", "asked").unwrap();
        let sink = collected.clone();
        local.add_sink("collect", move || Ok(Collect(sink)), "asked").unwrap();

        let report = local.run(Arc::new(AtomicBool::new(false))).unwrap();
        let expected: Vec<f32> = (0..FRAMES).map(|f| 2.0 * f as f32).collect();
        assert_eq!(*collected.lock().unwrap(), expected);
        assert!(side_first.lock().unwrap().iter().all(|&first| first));
        assert_eq!(report["asker"].errors, 0);
        assert_eq!(report["doubler"].frames_out, FRAMES);
    }

    #[test]
    fn a_stage_that_cannot_be_built_stops_the_graph_and_is_named() {
        let mut local = LocalGraph::new();
        local.edge("raw", 1, LocalOverflow::Block);
        local.add_source("counter", || Ok(Counter(0, u64::MAX)), "raw", None).unwrap();
        local.add_sink("broken", || Err::<Collect, _>("no such model".into()), "raw").unwrap();
        let err = local.run(Arc::new(AtomicBool::new(false))).unwrap_err();
        assert_eq!(crate::error_chain(&err), "stage `broken`: cannot build from its parameters: no such model");
    }
}
