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

use crate::liveness::Liveness;
use crate::stage::{EmitError, Emitter, Input, Sink, Source, SourceStep, Transform};

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

/// One reader's bounded queue.
#[derive(Debug)]
struct Queue<H> {
    state: Mutex<QueueState<H>>,
    changed: Condvar,
    capacity: usize,
    overflow: LocalOverflow,
}

#[derive(Debug)]
struct QueueState<H> {
    messages: VecDeque<(H, Vec<f32>)>,
    /// Publishers still attached; the stream ends when it reaches 0.
    publishers: usize,
}

impl<H> Queue<H> {
    fn push(&self, message: (H, Vec<f32>), stop: &AtomicBool) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        while state.messages.len() >= self.capacity {
            match self.overflow {
                LocalOverflow::DropOldest => {
                    state.messages.pop_front();
                }
                LocalOverflow::Block => {
                    if stop.load(Ordering::Relaxed) {
                        return;
                    }
                    state = self.changed.wait_timeout(state, STOP_POLL).unwrap_or_else(|e| e.into_inner()).0;
                }
            }
        }
        state.messages.push_back(message);
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
        self.changed.notify_all();
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
        let expected = header.payload_len().map_err(|e| EmitError(e.to_string()))?;
        if expected != len {
            return Err(EmitError(format!("{}: payload of {len} values, the header announces {expected}", H::NAME)));
        }
        if let Some(slot) = self.slot {
            header.header_mut().stamps.stamp(slot);
        }
        let mut payload = vec![0.0f32; len];
        fill(&mut payload);
        self.liveness.send_started();
        if let Some((last, others)) = self.readers.split_last() {
            for queue in others {
                queue.push((header, payload.clone()), self.stop);
            }
            last.push((header, payload), self.stop);
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

type StageThread = Box<dyn FnOnce(Arc<AtomicBool>) + Send>;
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
        Self { edges: HashMap::new(), specs: HashMap::new(), pending: Vec::new() }
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
        let (capacity, overflow) =
            *self.specs.get(name).ok_or_else(|| LocalGraphError::Undeclared { edge: name.to_string() })?;
        let queue = Arc::new(Queue {
            state: Mutex::new(QueueState { messages: VecDeque::new(), publishers: 0 }),
            changed: Condvar::new(),
            capacity,
            overflow,
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

    pub fn add_source<S: Source + Send + 'static>(
        &mut self,
        name: &str,
        mut source: S,
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
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    pub fn add_transform<T: Transform + Send + 'static>(
        &mut self,
        name: &str,
        mut stage: T,
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
                let mut emitter = LocalEmitter { readers, slot: T::SLOT, liveness: &live, stop: &stop };
                while let Some((header, payload)) = queue.pop(&stop) {
                    live.count_received(header.header().frame_id);
                    let started = Instant::now();
                    live.work_started();
                    if let Err(err) = stage.process(Input { header: &header, payload: &payload }, &mut emitter) {
                        live.count_error();
                        tracing::warn!(%err, "process failed; frame skipped");
                    }
                    live.count_errors(stage.take_rejected());
                    live.work_finished(started.elapsed());
                }
            })
        });
        self.defer(name, liveness, run);
        Ok(())
    }

    pub fn add_sink<K: Sink + Send + 'static>(
        &mut self,
        name: &str,
        mut sink: K,
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
                if let Err(err) = sink.finish() {
                    tracing::error!(%err, "sink could not finish");
                }
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
    pub fn run(self, stop: Arc<AtomicBool>) -> LocalReport {
        // Every publisher attaches to its readers before any thread starts,
        // so no reader mistakes "not started yet" for "finished".
        let threads: Vec<(String, Arc<Liveness>, StageThread)> =
            self.pending.into_iter().map(|(name, live, deferred)| (name, live, deferred(&self.edges))).collect();
        let handles: Vec<(String, Arc<Liveness>, JoinHandle<()>)> = threads
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
        handles
            .into_iter()
            .map(|(name, live, handle)| {
                if handle.join().is_err() {
                    live.count_error();
                    tracing::error!(stage = %name, "stage thread panicked");
                }
                live.set_state(StageState::Finished);
                (name, live.heartbeat())
            })
            .collect()
    }
}

struct PendingPublisher<H> {
    edge: String,
    _marker: std::marker::PhantomData<fn() -> H>,
}
