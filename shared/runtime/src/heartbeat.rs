//! The thread that publishes a stage's heartbeat.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use poseflow_contracts::{Heartbeat, StageState};
use poseflow_transport::{EdgeOptions, Overflow, Publisher, create_node};

use crate::RuntimeError;
use crate::liveness::Liveness;

/// SIGINT/SIGTERM go to the main thread, whose WaitSet turns them into a
/// clean shutdown; this thread must neither receive nor consume them.
fn block_termination_signals() {
    // SAFETY: plain libc calls on a local, initialised signal set; they only
    // change this thread's mask.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, libc::SIGINT);
        libc::sigaddset(&mut set, libc::SIGTERM);
        libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut());
    }
}

/// How long the last heartbeat waits for the supervisor to take it.
const FINAL_HEARTBEAT_TIMEOUT: Duration = Duration::from_secs(1);

#[derive(Debug)]
pub(crate) struct HeartbeatThread {
    stop: Arc<AtomicBool>,
    handle: JoinHandle<()>,
}

impl HeartbeatThread {
    /// Starts publishing on `service` every `period`. Returns once the
    /// publisher exists, so start-up failures surface here.
    pub fn spawn(stage: &str, service: &str, period: Duration, liveness: Arc<Liveness>) -> Result<Self, RuntimeError> {
        let stop = Arc::new(AtomicBool::new(false));
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let handle = std::thread::Builder::new()
            .name("heartbeat".into())
            .spawn({
                let (stop, node_name, service) = (stop.clone(), format!("{stage}-heartbeat"), service.to_string());
                move || {
                    block_termination_signals();
                    // iceoryx2 ports are bound to the thread that made them.
                    let setup = create_node(&node_name).and_then(|node| {
                        let options = EdgeOptions { queue: 1, overflow: Overflow::DropOldest, max_payload_len: 1 };
                        Publisher::<Heartbeat>::create(&node, &service, &options).map(|p| (node, p))
                    });
                    let (_node, publisher) = match setup {
                        Ok(ok) => {
                            let _ = ready_tx.send(Ok(()));
                            ok
                        }
                        Err(err) => {
                            let _ = ready_tx.send(Err(err));
                            return;
                        }
                    };
                    let beat = || {
                        if let Err(err) = publisher.publish(liveness.heartbeat(), 0, |_| {}) {
                            tracing::warn!(%err, "heartbeat not sent");
                        }
                    };
                    // Runs until the main thread has finished (after a stream
                    // ended or SIGINT/SIGTERM) and asks for the last beat.
                    while !stop.load(Ordering::Relaxed) {
                        beat();
                        std::thread::park_timeout(period);
                    }
                    // The final counters travel with the end-of-stream
                    // handshake: a sample still queued when its publisher
                    // exits is lost with it.
                    liveness.set_state(StageState::Finished);
                    beat();
                    if let Err(err) = publisher.end_of_stream(FINAL_HEARTBEAT_TIMEOUT) {
                        tracing::warn!(%err, "final heartbeat not acknowledged");
                    }
                }
            })
            .map_err(RuntimeError::HeartbeatThread)?;
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(Self { stop, handle }),
            Ok(Err(err)) => Err(err.into()),
            Err(_) => Err(RuntimeError::HeartbeatThreadDied),
        }
    }

    /// Sends the final heartbeat and joins the thread.
    pub fn finish(self) {
        self.stop.store(true, Ordering::Relaxed);
        self.handle.thread().unpark();
        let _ = self.handle.join();
    }
}

/// The heartbeat of a process that runs its own loop rather than one of
/// the stage kinds (the Zenoh bridge), so its supervisor reports and
/// watches it like any stage: counters, liveness, the final beat.
#[derive(Debug)]
pub struct ProcessHeartbeat {
    liveness: Arc<Liveness>,
    thread: HeartbeatThread,
}

impl ProcessHeartbeat {
    /// Starts beating on the wiring's heartbeat service.
    pub fn start(wiring: &poseflow_graph::StageWiring) -> Result<Self, RuntimeError> {
        let liveness = Arc::new(Liveness::new());
        liveness.mark_built();
        let period = Duration::from_millis(wiring.heartbeat_ms);
        let thread = HeartbeatThread::spawn(&wiring.stage, &wiring.heartbeat_service, period, liveness.clone())?;
        Ok(Self { liveness, thread })
    }

    /// One message taken in.
    pub fn received(&self) {
        self.liveness.count_in();
    }

    /// One message passed on.
    pub fn sent(&self) {
        self.liveness.count_sent();
    }

    /// Messages known lost on the way in.
    pub fn dropped(&self, n: u64) {
        self.liveness.count_dropped(n);
    }

    /// One message refused (and logged by the caller).
    pub fn error(&self) {
        self.liveness.count_error();
    }

    /// Sends the final heartbeat and stops.
    pub fn finish(self) {
        self.thread.finish();
    }
}
