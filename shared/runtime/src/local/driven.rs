//! A started [`super::LocalGraph`] driven from outside: messages go in
//! through a [`Feed`], results come out through a [`Collector`], and
//! [`RunningGraph::settle`] says when everything fed so far has been
//! handled by every stage.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use poseflow_contracts::{MessageHeader, StageState};

use super::queue::{InFlight, Queue, push_all};
use super::{LocalReport, StageEnd, check_len};
use crate::call::close_endpoint;
use crate::error::RuntimeError;
use crate::liveness::Liveness;
use crate::stage::EmitError;

/// Why a driven graph could not take a message or settle.
#[derive(Debug, thiserror::Error)]
pub enum DriveError {
    #[error("edge `{edge}`: the graph has not been started")]
    NotStarted { edge: String },

    #[error("the graph has stopped")]
    Stopped,

    #[error("edge `{edge}`: the message breaks its contract")]
    Message {
        edge: String,
        #[source]
        source: EmitError,
    },

    #[error("the graph did not settle within {0:?}: a stage is stuck or too slow")]
    Timeout(Duration),

    #[error("stage `{stage}` ended while the graph was driven")]
    StageEnded { stage: String },

    #[error(transparent)]
    Stage(#[from] RuntimeError),
}

struct Attached<H> {
    readers: Vec<Arc<Queue<H>>>,
    stop: Arc<AtomicBool>,
}

/// Sends messages into one edge of a driven graph (see
/// [`super::LocalGraph::feed`]).
pub struct Feed<H> {
    edge: String,
    attached: Arc<OnceLock<Attached<H>>>,
}

impl<H> std::fmt::Debug for Feed<H> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Feed").field("edge", &self.edge).finish()
    }
}

impl<H: MessageHeader> Feed<H> {
    pub(super) fn new(edge: &str) -> Self {
        Self { edge: edge.to_string(), attached: Arc::new(OnceLock::new()) }
    }

    /// What the graph calls when it starts: the edge's readers.
    pub(super) fn attachment(&self) -> impl FnOnce(Vec<Arc<Queue<H>>>, Arc<AtomicBool>) + use<H> {
        let attached = self.attached.clone();
        move |readers, stop| {
            let _ = attached.set(Attached { readers, stop });
        }
    }

    /// Queues `payload` under `header` for every reader of the edge,
    /// waiting while a blocking reader's queue is full.
    pub fn send(&self, header: H, payload: Vec<f32>) -> Result<(), DriveError> {
        let attached = self.attached.get().ok_or_else(|| DriveError::NotStarted { edge: self.edge.clone() })?;
        check_len(&header, payload.len()).map_err(|source| DriveError::Message { edge: self.edge.clone(), source })?;
        for queue in &attached.readers {
            queue.wait_for_room(&attached.stop);
        }
        if attached.stop.load(Ordering::Relaxed) {
            return Err(DriveError::Stopped);
        }
        push_all(&attached.readers, (header, payload));
        Ok(())
    }
}

impl<H> Drop for Feed<H> {
    fn drop(&mut self) {
        if let Some(attached) = self.attached.get() {
            for queue in &attached.readers {
                queue.detach_publisher();
            }
        }
    }
}

/// Keeps the messages of one edge of a driven graph (see
/// [`super::LocalGraph::collect`]).
pub struct Collector<H> {
    queue: Arc<Queue<H>>,
}

impl<H> std::fmt::Debug for Collector<H> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Collector").finish()
    }
}

impl<H> Collector<H> {
    pub(super) fn new(queue: Arc<Queue<H>>) -> Self {
        Self { queue }
    }

    /// Every message collected since the last call, in arrival order.
    pub fn drain(&self) -> Vec<(H, Vec<f32>)> {
        self.queue.drain()
    }
}

impl<H> Drop for Collector<H> {
    fn drop(&mut self) {
        self.queue.close();
    }
}

type StageHandle = (String, Arc<Liveness>, JoinHandle<StageEnd>);

/// The stages of a started graph, each on its own thread.
pub struct RunningGraph {
    stages: Vec<StageHandle>,
    services: Vec<String>,
    stop: Arc<AtomicBool>,
    in_flight: Arc<InFlight>,
}

impl std::fmt::Debug for RunningGraph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RunningGraph").field("stages", &self.stages.len()).finish()
    }
}

impl RunningGraph {
    pub(super) fn new(
        stages: Vec<StageHandle>,
        services: Vec<String>,
        stop: Arc<AtomicBool>,
        in_flight: Arc<InFlight>,
    ) -> Self {
        Self { stages, services, stop, in_flight }
    }

    /// Waits until every stage has been built (loaded its model, opened
    /// its ports); the first stage that could not be built is the error.
    pub fn wait_built(&mut self, timeout: Duration) -> Result<(), DriveError> {
        let deadline = Instant::now() + timeout;
        while !self.stages.iter().all(|(_, live, _)| live.is_built()) {
            if let Some(err) = self.ended_stage() {
                return Err(err);
            }
            if Instant::now() >= deadline {
                return Err(DriveError::Timeout(timeout));
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        Ok(())
    }

    /// Waits until every message fed so far, and everything it caused, has
    /// been handled by its stages (the collectors hold the results). Only
    /// meaningful when the graph's sources are all [`Feed`]s.
    pub fn settle(&mut self, timeout: Duration) -> Result<(), DriveError> {
        let deadline = Instant::now() + timeout;
        let stages = &self.stages;
        let stop = &self.stop;
        let mut ended = || stop.load(Ordering::Relaxed) || stages.iter().any(|(_, _, handle)| handle.is_finished());
        if self.in_flight.wait_settled(deadline, &mut ended) {
            return Ok(());
        }
        Err(self.ended_stage().unwrap_or(DriveError::Timeout(timeout)))
    }

    /// Why the graph cannot go on, if it cannot: a stage thread that ended
    /// (stopping the others), or the stop flag.
    fn ended_stage(&mut self) -> Option<DriveError> {
        if let Some(index) = self.stages.iter().position(|(_, _, handle)| handle.is_finished()) {
            let (stage, live, handle) = self.stages.remove(index);
            live.set_state(StageState::Finished);
            self.stop.store(true, Ordering::Relaxed);
            return Some(match handle.join() {
                Ok(Err(source)) => DriveError::Stage(RuntimeError::Build { stage, source }),
                _ => DriveError::StageEnded { stage },
            });
        }
        self.stop.load(Ordering::Relaxed).then_some(DriveError::Stopped)
    }

    /// Every stage's counters now.
    pub fn counters(&self) -> LocalReport {
        self.stages.iter().map(|(name, live, _)| (name.clone(), live.heartbeat())).collect()
    }

    /// Asks every stage to stop (the graph's `stop` flag).
    pub fn stop(&self) {
        self.stop.store(true, Ordering::Relaxed);
    }

    /// Waits for every stage to end (the feeds dropped and everything
    /// drained, or [`Self::stop`]) and returns their final counters; the
    /// first stage that could not be built is the error.
    pub fn finish(mut self) -> Result<LocalReport, RuntimeError> {
        self.join_all()
    }

    fn join_all(&mut self) -> Result<LocalReport, RuntimeError> {
        let mut failure = None;
        let mut report = LocalReport::new();
        for (name, live, handle) in self.stages.drain(..) {
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
        for service in self.services.drain(..) {
            close_endpoint(&service);
        }
        match failure {
            Some(err) => Err(err),
            None => Ok(report),
        }
    }
}

impl Drop for RunningGraph {
    /// A graph dropped while running is stopped, so no stage thread
    /// outlives it.
    fn drop(&mut self) {
        if !self.stages.is_empty() {
            self.stop();
            let _ = self.join_all();
        }
    }
}
