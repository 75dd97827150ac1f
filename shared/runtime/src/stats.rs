//! Counters and latency of one stage process, reported in its heartbeat.

use std::time::Duration;

use hdrhistogram::Histogram;
use poseflow_contracts::{Header, Heartbeat, StageState};

#[derive(Debug)]
pub(crate) struct Stats {
    pub frames_in: u64,
    pub frames_out: u64,
    pub dropped: u64,
    pub errors: u64,
    last_frame: Option<u64>,
    latency_us: Histogram<u64>,
}

impl Stats {
    pub fn new() -> Self {
        Self {
            frames_in: 0,
            frames_out: 0,
            dropped: 0,
            errors: 0,
            last_frame: None,
            // 1 µs .. 60 s at 3 significant digits.
            latency_us: Histogram::new_with_bounds(1, 60_000_000, 3)
                .expect("valid histogram bounds"),
        }
    }

    /// Counts frames missing between the previous frame id and this one. A
    /// smaller id means the source restarted its numbering; that is not a drop.
    pub fn observe_frame(&mut self, frame_id: u64) {
        if let Some(last) = self.last_frame
            && frame_id > last + 1
        {
            let missing = frame_id - last - 1;
            self.dropped += missing;
            tracing::warn!(frame = frame_id, missing, "frames missing upstream");
        }
        self.last_frame = Some(frame_id);
    }

    pub fn record_latency(&mut self, elapsed: Duration) {
        self.latency_us
            .saturating_record(elapsed.as_micros().max(1) as u64);
    }

    pub fn heartbeat(&self, state: StageState) -> Heartbeat {
        let mut header = Header::new(self.last_frame.unwrap_or(0), 0);
        header.stamps.stamp(poseflow_contracts::Stage::Source);
        let quantile = |q| {
            self.latency_us
                .value_at_quantile(q)
                .min(u64::from(u32::MAX)) as u32
        };
        Heartbeat {
            header,
            pid: std::process::id(),
            state: state as u32,
            frames_in: self.frames_in,
            frames_out: self.frames_out,
            dropped: self.dropped,
            errors: self.errors,
            latency_p50_us: quantile(0.5),
            latency_p99_us: quantile(0.99),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_count_as_drops_and_restarts_do_not() {
        let mut stats = Stats::new();
        for id in [0, 1, 2, 5, 6, 0, 1] {
            stats.observe_frame(id);
        }
        assert_eq!(stats.dropped, 2);
    }

    #[test]
    fn latency_quantiles_reach_the_heartbeat() {
        let mut stats = Stats::new();
        for us in 1..=100 {
            stats.record_latency(Duration::from_micros(us));
        }
        let beat = stats.heartbeat(StageState::Running);
        assert_eq!(beat.latency_p50_us, 50);
        assert_eq!(beat.latency_p99_us, 99);
        assert_eq!(beat.state, StageState::Running as u32);
    }
}
