//! Counters and timing of one stage process, shared between the thread
//! doing the work and the thread publishing heartbeats.
//!
//! The heartbeat has its own thread so that a stage waiting on back-pressure
//! (a full downstream queue) still reports in; hang detection then looks at
//! `busy_us`, the time spent in the stage's own code, not at silence.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering::Relaxed};
use std::time::Duration;

use hdrhistogram::Histogram;
use poseflow_contracts::{Header, Heartbeat, StageState, flags, monotonic_ns};

#[derive(Debug)]
pub(crate) struct Liveness {
    frames_in: AtomicU64,
    frames_out: AtomicU64,
    dropped: AtomicU64,
    errors: AtomicU64,
    /// `u64::MAX` until the first frame.
    last_frame: AtomicU64,
    state: AtomicU32,
    /// Monotonic ns at which the current unit of work began; 0 when idle.
    work_started_ns: AtomicU64,
    /// Time spent sending during the current unit of work.
    work_send_ns: AtomicU64,
    /// Monotonic ns at which the current send began; 0 when not sending.
    send_started_ns: AtomicU64,
    /// Process time per frame, µs: one sample per input frame (per step of
    /// a source), not per message. A stage that batches a frame's objects
    /// holds most of its inputs in a microsecond and works on the last, and
    /// a server's or a caller's work comes in requests and flushes, not
    /// inputs; per message, the median would be the holding.
    latency_us: Mutex<Histogram<u64>>,
    /// The frame whose work is being summed, and its busy time so far.
    open_frame: Mutex<OpenFrame>,
    /// This process replaced a dead one and has not yet said so downstream.
    restart_unannounced: AtomicBool,
    /// The stage has been built (an in-process stage builds on its thread).
    built: AtomicBool,
}

/// The work of the latest input frame: its inputs, and the flushes and
/// requests handled until the next frame's first input (a request is
/// counted to the frame the stage last received, whichever frame it asks
/// for: over a run the sums are the stage's time per frame).
#[derive(Debug, Default)]
struct OpenFrame {
    frame_id: Option<u64>,
    busy: Duration,
}

fn micros(ns: u64) -> u32 {
    (ns / 1000).min(u64::from(u32::MAX)) as u32
}

impl Liveness {
    /// Lets a transform run what it batched ([`crate::Transform::flush`]),
    /// timed and counted as an input is.
    pub fn flush<T: crate::Transform>(
        &self,
        stage: &mut T,
        output: &mut dyn crate::Emitter<T::Out>,
        reason: crate::Flush,
    ) {
        let started = std::time::Instant::now();
        self.work_started();
        if let Err(err) = stage.flush(output, reason) {
            self.count_error();
            tracing::warn!(err = %crate::error_chain(&err), "flush failed; its frames skipped");
        }
        self.count_errors(stage.take_rejected());
        self.work_finished(started.elapsed());
    }

    pub fn new() -> Self {
        Self {
            frames_in: AtomicU64::new(0),
            frames_out: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            errors: AtomicU64::new(0),
            last_frame: AtomicU64::new(u64::MAX),
            state: AtomicU32::new(StageState::Running as u32),
            work_started_ns: AtomicU64::new(0),
            work_send_ns: AtomicU64::new(0),
            send_started_ns: AtomicU64::new(0),
            // 1 µs .. 60 s at 3 significant digits.
            latency_us: Mutex::new(Histogram::new_with_bounds(1, 60_000_000, 3).expect("valid histogram bounds")),
            open_frame: Mutex::new(OpenFrame::default()),
            restart_unannounced: AtomicBool::new(false),
            built: AtomicBool::new(false),
        }
    }

    pub fn mark_built(&self) {
        self.built.store(true, Relaxed);
    }

    pub fn is_built(&self) -> bool {
        self.built.load(Relaxed)
    }

    /// A restarted process flags its first output so that stages downstream
    /// drop what they cached from the frames before the restart.
    pub fn restarted(&self) {
        self.restart_unannounced.store(true, Relaxed);
    }

    /// Flags `header` [`flags::UPSTREAM_RESTARTED`] if this process has not
    /// announced its restart yet; returns whether it did, so a send that
    /// fails can [`Self::restarted`] again.
    pub fn announce_restart(&self, header: &mut Header) -> bool {
        let announce = self.restart_unannounced.swap(false, Relaxed);
        if announce {
            header.flags |= flags::UPSTREAM_RESTARTED;
        }
        announce
    }

    /// `Finished` also closes the last frame's process time.
    pub fn set_state(&self, state: StageState) {
        if state == StageState::Finished {
            self.close_frame();
        }
        self.state.store(state as u32, Relaxed);
    }

    pub fn count_error(&self) {
        self.count_errors(1);
    }

    pub fn count_errors(&self, n: u64) {
        self.errors.fetch_add(n, Relaxed);
    }

    pub fn count_sent(&self) {
        self.frames_out.fetch_add(1, Relaxed);
    }

    /// Counts an accepted input and the frames missing between the previous
    /// frame id and this one. A smaller id means the source restarted its
    /// numbering; that is not a drop.
    pub fn count_received(&self, frame_id: u64) {
        self.frames_in.fetch_add(1, Relaxed);
        self.open(frame_id);
        let last = self.last_frame.swap(frame_id, Relaxed);
        if last != u64::MAX && frame_id > last + 1 {
            let missing = frame_id - last - 1;
            self.dropped.fetch_add(missing, Relaxed);
            tracing::warn!(frame = frame_id, missing, "frames missing upstream");
        }
    }

    /// Counts an accepted input whose gaps the caller counts itself
    /// ([`Self::count_dropped`]): a process reading several edges.
    pub fn count_in(&self) {
        self.frames_in.fetch_add(1, Relaxed);
    }

    pub fn count_dropped(&self, n: u64) {
        self.dropped.fetch_add(n, Relaxed);
    }

    pub fn work_started(&self) {
        self.work_send_ns.store(0, Relaxed);
        self.work_started_ns.store(monotonic_ns(), Relaxed);
    }

    /// Ends a unit of work (an input, a flush, a request): its time, less
    /// its sends (a full queue downstream is not this stage's cost),
    /// counts to the open frame.
    pub fn work_finished(&self, elapsed: Duration) {
        self.work_started_ns.store(0, Relaxed);
        let sending = Duration::from_nanos(self.work_send_ns.load(Relaxed));
        self.open_frame.lock().unwrap_or_else(|e| e.into_inner()).busy += elapsed.saturating_sub(sending);
    }

    /// A frame's first input: the previous frame's work is one sample.
    fn open(&self, frame_id: u64) {
        let mut open = self.open_frame.lock().unwrap_or_else(|e| e.into_inner());
        if open.frame_id != Some(frame_id) {
            self.close(&mut open);
            open.frame_id = Some(frame_id);
        }
    }

    /// No more input: the last frame's work is a sample.
    fn close_frame(&self) {
        self.close(&mut self.open_frame.lock().unwrap_or_else(|e| e.into_inner()));
    }

    fn close(&self, open: &mut OpenFrame) {
        let busy = std::mem::take(&mut open.busy);
        if open.frame_id.take().is_some() {
            self.record(busy);
        }
    }

    fn record(&self, busy: Duration) {
        let mut histogram = self.latency_us.lock().unwrap_or_else(|e| e.into_inner());
        histogram.saturating_record(busy.as_micros().max(1) as u64);
    }

    /// The unit of work turned out to be a wait with nothing to do: not
    /// busy time, and not a latency sample.
    pub fn work_abandoned(&self) {
        self.work_started_ns.store(0, Relaxed);
    }

    /// Ends a source's call: a sample (one frame) unless it was idle.
    pub fn source_step_finished(&self, step: Option<crate::SourceStep>, elapsed: Duration) {
        self.work_abandoned();
        if step != Some(crate::SourceStep::Idle) {
            self.record(elapsed.saturating_sub(Duration::from_nanos(self.work_send_ns.load(Relaxed))));
        }
    }

    pub fn send_started(&self) {
        self.send_started_ns.store(monotonic_ns(), Relaxed);
    }

    pub fn send_finished(&self) {
        let started = self.send_started_ns.swap(0, Relaxed);
        if started != 0 {
            self.work_send_ns.fetch_add(monotonic_ns().saturating_sub(started), Relaxed);
        }
    }

    /// A consistent-enough snapshot for the heartbeat (fields are read one
    /// by one; a counter may be one message ahead of another).
    pub fn heartbeat(&self) -> Heartbeat {
        let now = monotonic_ns();
        let last = self.last_frame.load(Relaxed);
        let mut header = Header::new(if last == u64::MAX { 0 } else { last }, 0);
        header.stamps.ns[0] = now;
        let send_started = self.send_started_ns.load(Relaxed);
        let blocked = if send_started == 0 { 0 } else { now.saturating_sub(send_started) };
        let work_started = self.work_started_ns.load(Relaxed);
        let busy = if work_started == 0 {
            0
        } else {
            now.saturating_sub(work_started).saturating_sub(self.work_send_ns.load(Relaxed)).saturating_sub(blocked)
        };
        let histogram = self.latency_us.lock().unwrap_or_else(|e| e.into_inner());
        let quantile = |q| histogram.value_at_quantile(q).min(u64::from(u32::MAX)) as u32;
        Heartbeat {
            header,
            pid: std::process::id(),
            state: self.state.load(Relaxed),
            frames_in: self.frames_in.load(Relaxed),
            frames_out: self.frames_out.load(Relaxed),
            dropped: self.dropped.load(Relaxed),
            errors: self.errors.load(Relaxed),
            latency_p50_us: quantile(0.5),
            latency_p99_us: quantile(0.99),
            busy_us: micros(busy),
            blocked_us: micros(blocked),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_count_as_drops_and_restarts_do_not() {
        let liveness = Liveness::new();
        for id in [0, 1, 2, 5, 6, 0, 1] {
            liveness.count_received(id);
        }
        let beat = liveness.heartbeat();
        assert_eq!(beat.dropped, 2);
        assert_eq!(beat.frames_in, 7);
        assert_eq!(beat.header.frame_id, 1);
    }

    #[test]
    fn a_restart_is_announced_on_one_output_only() {
        let liveness = Liveness::new();
        let mut header = Header::new(0, 1);
        assert!(!liveness.announce_restart(&mut header), "a first process has nothing to announce");
        liveness.restarted();
        assert!(liveness.announce_restart(&mut header));
        assert!(header.has_flag(flags::UPSTREAM_RESTARTED));
        let mut next = Header::new(1, 1);
        assert!(!liveness.announce_restart(&mut next));
        assert_eq!(next.flags, 0);
    }

    fn work(liveness: &Liveness, us: u64) {
        liveness.work_started();
        liveness.work_finished(Duration::from_micros(us));
    }

    #[test]
    fn latency_quantiles_reach_the_heartbeat() {
        let liveness = Liveness::new();
        for us in 1..=100 {
            liveness.count_received(us);
            work(&liveness, us);
        }
        liveness.set_state(StageState::Finished);
        let beat = liveness.heartbeat();
        assert_eq!((beat.latency_p50_us, beat.latency_p99_us), (50, 99));
        assert_eq!(beat.busy_us, 0, "idle between messages");
    }

    #[test]
    fn process_time_is_per_frame_whatever_the_messages() {
        let liveness = Liveness::new();
        // Per frame: seven inputs held in 1 µs, the last runs the batch
        // (1000 µs), then an idle flush (1 µs) and two requests (300 µs each).
        for frame in 0..10 {
            for _ in 0..7 {
                liveness.count_received(frame);
                work(&liveness, 1);
            }
            liveness.count_received(frame);
            work(&liveness, 1000);
            work(&liveness, 1);
            work(&liveness, 300);
            work(&liveness, 300);
        }
        assert_eq!(liveness.heartbeat().latency_p50_us, 1608, "nine frames closed by the next one's input");
        liveness.set_state(StageState::Finished);
        liveness.set_state(StageState::Finished);
        let beat = liveness.heartbeat();
        assert_eq!((beat.latency_p50_us, beat.latency_p99_us), (1608, 1608));
        assert_eq!(liveness.latency_us.lock().unwrap().len(), 10, "one sample per frame");
    }

    #[test]
    fn a_source_step_is_one_frame_and_an_idle_one_none() {
        let liveness = Liveness::new();
        liveness.work_started();
        liveness.source_step_finished(Some(crate::SourceStep::Idle), Duration::from_micros(5));
        liveness.work_started();
        liveness.source_step_finished(Some(crate::SourceStep::Continue), Duration::from_micros(700));
        let beat = liveness.heartbeat();
        assert_eq!((beat.latency_p50_us, beat.busy_us), (700, 0));
        assert_eq!(liveness.latency_us.lock().unwrap().len(), 1);
    }

    #[test]
    fn time_blocked_in_a_send_is_not_busy_time() {
        let liveness = Liveness::new();
        liveness.work_started();
        std::thread::sleep(Duration::from_millis(20));
        liveness.send_started();
        std::thread::sleep(Duration::from_millis(60));
        let beat = liveness.heartbeat();
        assert!(beat.blocked_us >= 60_000, "{beat:?}");
        assert!(beat.busy_us >= 20_000 && beat.busy_us < 60_000, "{beat:?}");
        liveness.send_finished();
        liveness.count_received(0);
        liveness.work_finished(Duration::from_millis(80));
        liveness.set_state(StageState::Finished);
        let process_us = liveness.heartbeat().latency_p50_us;
        assert!((19_000..60_000).contains(&process_us), "the send left out of the process time: {process_us} µs");
    }
}
