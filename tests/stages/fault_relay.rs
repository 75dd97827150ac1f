//! A negating relay (the smoke relay) that misbehaves once, for the fault
//! injection tests: at frame `at_frame`, unless the `marker` directory
//! exists (it is created first, so a restarted process behaves),
//!
//! - `fault = "crash"`: panics mid-frame (input taken, nothing emitted;
//!   the process exits with status 101);
//! - `fault = "hang"`: never returns from that frame;
//! - `fault = "ignore-sigterm"`: ignores SIGTERM from then on and never
//!   returns from that frame, so only SIGKILL ends it;
//! - `fault = "flood"`: emits `copies` copies of that frame and of every
//!   later one (the same frame id and payload) into its bounded queue.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use poseflow_contracts::{HypothesesHeader, MessageHeader};
use poseflow_graph::StageWiring;
use poseflow_runtime::{Emitter, Input, Transform};
use poseflow_smoke::{NegatingRelay, SmokeError};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fault {
    Crash,
    Hang,
    IgnoreSigterm,
    Flood,
}

#[derive(Debug)]
struct FaultRelay {
    fault: Fault,
    at_frame: u64,
    marker: PathBuf,
    copies: usize,
    flooding: bool,
}

impl FaultRelay {
    fn from_wiring(wiring: &StageWiring) -> Result<Self, String> {
        let param = |key: &str| wiring.params.get(key).ok_or_else(|| format!("param `{key}`: missing"));
        let fault = match param("fault")?.as_str() {
            Some("crash") => Fault::Crash,
            Some("hang") => Fault::Hang,
            Some("ignore-sigterm") => Fault::IgnoreSigterm,
            Some("flood") => Fault::Flood,
            other => return Err(format!("param `fault`: {other:?}: expected crash, hang, ignore-sigterm or flood")),
        };
        let at_frame = param("at_frame")?.as_u64().ok_or("param `at_frame`: expected a frame id")?;
        let marker = PathBuf::from(param("marker")?.as_str().ok_or("param `marker`: expected a path")?);
        let copies = wiring.params.get("copies").and_then(serde_json::Value::as_u64).unwrap_or(1) as usize;
        Ok(Self { fault, at_frame, marker, copies, flooding: false })
    }

    /// True once: the first time any process of this stage reaches the
    /// faulty frame.
    fn first_time(&self, frame: u64) -> bool {
        frame >= self.at_frame && std::fs::create_dir(&self.marker).is_ok()
    }
}

impl Transform for FaultRelay {
    type In = HypothesesHeader;
    type Out = HypothesesHeader;
    type Error = SmokeError;
    const SLOT: Option<poseflow_contracts::StampSlot> = NegatingRelay::SLOT;

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        output: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), SmokeError> {
        let frame = input.header.header().frame_id;
        if !self.flooding && self.first_time(frame) {
            match self.fault {
                Fault::Crash => panic!("fault-relay: injected crash at frame {frame}"),
                Fault::Hang => loop {
                    std::thread::sleep(Duration::from_secs(1));
                },
                Fault::IgnoreSigterm => {
                    // SAFETY: replacing a signal disposition; no handler runs.
                    unsafe { libc::signal(libc::SIGTERM, libc::SIG_IGN) };
                    loop {
                        std::thread::sleep(Duration::from_secs(1));
                    }
                }
                Fault::Flood => self.flooding = true,
            }
        }
        let copies = if self.flooding { self.copies } else { 1 };
        for _ in 0..copies {
            NegatingRelay.process(Input { header: input.header, payload: input.payload }, output)?;
        }
        Ok(())
    }
}

fn main() -> ExitCode {
    poseflow_runtime::run_transform(FaultRelay::from_wiring)
}
