//! The in-process edges: one bounded queue per reader, the doorbell that
//! wakes a stage waiting on several of them, and the count of messages
//! still in flight that tells a driven graph it has settled.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use super::{LocalOverflow, STOP_POLL};

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

/// Messages queued for a stage and not yet handled by it, over the whole
/// graph. A stage emits a message's outputs before it reports the message
/// handled, so the count reaches zero only when nothing is left to do.
#[derive(Debug, Default)]
pub(crate) struct InFlight {
    count: Mutex<usize>,
    settled: Condvar,
}

impl InFlight {
    fn add(&self) {
        *self.count.lock().unwrap_or_else(|e| e.into_inner()) += 1;
    }

    fn remove(&self, messages: usize) {
        let mut count = self.count.lock().unwrap_or_else(|e| e.into_inner());
        *count = count.saturating_sub(messages);
        if *count == 0 {
            self.settled.notify_all();
        }
    }

    /// Waits until nothing is in flight; `false` if `deadline` passes or
    /// `give_up` says so first (checked every [`STOP_POLL`]).
    pub fn wait_settled(&self, deadline: Instant, give_up: &mut dyn FnMut() -> bool) -> bool {
        let mut count = self.count.lock().unwrap_or_else(|e| e.into_inner());
        while *count > 0 {
            let now = Instant::now();
            if now >= deadline || give_up() {
                return false;
            }
            let wait = STOP_POLL.min(deadline - now);
            count = self.settled.wait_timeout(count, wait).unwrap_or_else(|e| e.into_inner()).0;
        }
        true
    }
}

/// Queues `message` for every reader at once (all their locks held), so a
/// stage reading two of them (an input and a side input) never sees the
/// message on one before the other. A full blocking queue is waited for
/// before (see [`Queue::wait_for_room`]); a full drop-oldest one loses its
/// oldest message; a closed one drops it.
pub(crate) fn push_all<H: Clone>(readers: &[Arc<Queue<H>>], message: (H, Vec<f32>)) {
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
    if state.messages.len() >= queue.capacity && state.messages.pop_front().is_some() {
        queue.handled_many(1);
    }
    state.messages.push_back(message);
    if let Some(in_flight) = &queue.in_flight {
        in_flight.add();
    }
}

/// One reader's bounded queue.
#[derive(Debug)]
pub(crate) struct Queue<H> {
    pub(crate) state: Mutex<QueueState<H>>,
    changed: Condvar,
    capacity: usize,
    overflow: LocalOverflow,
    doorbell: Option<Arc<Doorbell>>,
    /// `None` for a reader outside the graph (a [`super::Collector`]),
    /// whose messages are results, not work.
    in_flight: Option<Arc<InFlight>>,
}

#[derive(Debug)]
pub(crate) struct QueueState<H> {
    messages: VecDeque<(H, Vec<f32>)>,
    /// Publishers still attached; the stream ends when it reaches 0.
    pub(crate) publishers: usize,
    /// The reader has ended: later messages are dropped, not queued, so no
    /// publisher waits for room that never comes.
    closed: bool,
}

impl<H> Queue<H> {
    pub fn new(
        capacity: usize,
        overflow: LocalOverflow,
        doorbell: Option<Arc<Doorbell>>,
        in_flight: Option<Arc<InFlight>>,
    ) -> Self {
        Self {
            state: Mutex::new(QueueState { messages: VecDeque::new(), publishers: 0, closed: false }),
            changed: Condvar::new(),
            capacity,
            overflow,
            doorbell,
            in_flight,
        }
    }

    fn ring(&self) {
        self.changed.notify_all();
        if let Some(doorbell) = &self.doorbell {
            doorbell.ring();
        }
    }

    /// The reader is done with a message it popped (its outputs are queued).
    pub fn handled(&self) {
        self.handled_many(1);
    }

    /// As [`Self::handled`], for `messages` at once.
    pub fn handled_many(&self, messages: usize) {
        if let Some(in_flight) = &self.in_flight {
            in_flight.remove(messages);
        }
    }

    /// Whether a message can be queued now without waiting.
    pub fn has_room(&self) -> bool {
        let state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.closed || self.overflow == LocalOverflow::DropOldest || state.messages.len() < self.capacity
    }

    /// Waits until [`Self::has_room`] or `stop`. Only the edge's one
    /// publisher queues here, so the room is still there when it pushes.
    pub fn wait_for_room(&self, stop: &AtomicBool) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        while self.overflow == LocalOverflow::Block
            && state.messages.len() >= self.capacity
            && !state.closed
            && !stop.load(Ordering::Relaxed)
        {
            state = self.changed.wait_timeout(state, STOP_POLL).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    pub fn try_pop(&self) -> Option<(H, Vec<f32>)> {
        let message = self.state.lock().unwrap_or_else(|e| e.into_inner()).messages.pop_front();
        if message.is_some() {
            self.changed.notify_all();
        }
        message
    }

    /// Every message queued so far, without waiting.
    pub fn drain(&self) -> Vec<(H, Vec<f32>)> {
        let drained: Vec<_> = self.state.lock().unwrap_or_else(|e| e.into_inner()).messages.drain(..).collect();
        self.changed.notify_all();
        drained
    }

    /// Every publisher is gone and the queue is drained.
    pub fn ended(&self) -> bool {
        let state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.publishers == 0 && state.messages.is_empty()
    }

    pub fn close(&self) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.closed = true;
        let dropped = state.messages.len();
        state.messages.clear();
        drop(state);
        self.handled_many(dropped);
        self.changed.notify_all();
    }

    /// The next message; `None` once every publisher is gone and the queue
    /// is drained, or when `stop` is set.
    pub fn pop(&self, stop: &AtomicBool) -> Option<(H, Vec<f32>)> {
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

    pub fn attach_publisher(&self) {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).publishers += 1;
    }

    pub fn detach_publisher(&self) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.publishers -= 1;
        drop(state);
        self.ring();
    }
}
