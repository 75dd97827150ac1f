//! Smoke-test stages: a counting source, a relay that negates, and a sink
//! that checks every value. Frame `f` carries the values [`value`]`(f, i)`,
//! so any corruption, loss or reordering on the way is detected exactly.
//!
//! `deploy/smoke.toml` wires them into a graph; run it to check the
//! transport, the supervisor and a machine's shared memory without a model.

use std::path::PathBuf;

use poseflow_contracts::{Header, HypothesesHeader, MessageHeader, POSE_LEN, StampSlot, flags};
use poseflow_graph::StageWiring;
use poseflow_runtime::{Emitter, Input, Registration, Sink, Source, SourceStep, Transform};

/// The smoke stages, by the executable names graph files give them.
pub fn registrations() -> Vec<Registration> {
    vec![
        Registration::source("smoke-source", CountingSource::from_wiring),
        Registration::transform("smoke-relay", |_| Ok::<_, std::convert::Infallible>(NegatingRelay)),
        Registration::sink("smoke-sink", CheckingSink::from_wiring),
    ]
}

/// The value at index `i` of frame `f`: an integer below 2²⁴, exact in f32.
pub fn value(frame: u64, index: usize) -> f32 {
    ((frame.wrapping_mul(7919) + index as u64 * 104_729) % 1_000_003) as f32
}

#[derive(Debug, thiserror::Error)]
pub enum SmokeError {
    #[error("frame {frame}: value {index} is {found}, expected {expected}")]
    Corrupted { frame: u64, index: usize, found: f32, expected: f32 },
    #[error(transparent)]
    Emit(#[from] poseflow_runtime::EmitError),
    #[error("cannot write report {path}")]
    Report { path: PathBuf, source: std::io::Error },
    #[error("param `{key}`: expected {expected}, got {found}")]
    Param { key: String, expected: &'static str, found: String },
}

fn param_u64(wiring: &StageWiring, key: &str, default: u64) -> Result<u64, SmokeError> {
    match wiring.params.get(key) {
        None => Ok(default),
        Some(v) => v.as_u64().ok_or_else(|| SmokeError::Param {
            key: key.into(),
            expected: "a non-negative integer",
            found: v.to_string(),
        }),
    }
}

/// Emits `frames` Hypotheses messages of `samples` poses each.
#[derive(Debug)]
pub struct CountingSource {
    next_frame: u64,
    frames: u64,
    samples: u32,
}

impl CountingSource {
    pub fn from_wiring(wiring: &StageWiring) -> Result<Self, SmokeError> {
        Ok(Self {
            next_frame: 0,
            frames: param_u64(wiring, "frames", 1000)?,
            samples: param_u64(wiring, "samples", 4)? as u32,
        })
    }
}

impl Source for CountingSource {
    type Out = HypothesesHeader;
    type Error = SmokeError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Source);

    fn next(&mut self, output: &mut dyn Emitter<HypothesesHeader>) -> Result<SourceStep, SmokeError> {
        if self.next_frame >= self.frames {
            return Ok(SourceStep::Finished);
        }
        let frame = self.next_frame;
        self.next_frame += 1;
        let header = HypothesesHeader {
            header: Header::new(frame, 1),
            sample_count: self.samples,
            step_count: 1,
            ..Default::default()
        };
        let len = self.samples as usize * POSE_LEN;
        output.emit(header, len, &mut |payload| {
            for (i, v) in payload.iter_mut().enumerate() {
                *v = value(frame, i);
            }
        })?;
        Ok(SourceStep::Continue)
    }
}

/// Negates every value, keeping header and stamps.
#[derive(Debug, Default)]
pub struct NegatingRelay;

impl Transform for NegatingRelay {
    type In = HypothesesHeader;
    type Out = HypothesesHeader;
    type Error = SmokeError;
    const SLOT: Option<StampSlot> = Some(StampSlot::Sampler);

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        output: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), SmokeError> {
        let payload = input.payload;
        output.emit(*input.header, payload.len(), &mut |out| {
            for (o, v) in out.iter_mut().zip(payload) {
                *o = -v;
            }
        })?;
        Ok(())
    }
}

/// What the checking sink saw, written as JSON when it finishes.
#[derive(Debug, Default, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SinkReport {
    pub received: u64,
    pub intact: u64,
    pub corrupted: u64,
    pub first_frame: Option<u64>,
    pub last_frame: Option<u64>,
    /// Frames missing between received ones (dropped upstream).
    pub gaps: u64,
    /// Received frames stamped by a stage after the source (the relay).
    pub relayed: u64,
    /// Frames flagged `UPSTREAM_RESTARTED`: one per restart of a stage
    /// upstream whose first output got through.
    #[serde(default)]
    pub restart_notices: u64,
}

/// Checks that every frame carries `-value(f, i)` (one negating relay).
#[derive(Debug)]
pub struct CheckingSink {
    /// Where to write the report as JSON; logged when absent.
    report_path: Option<PathBuf>,
    report: SinkReport,
}

impl CheckingSink {
    pub fn from_wiring(wiring: &StageWiring) -> Result<Self, SmokeError> {
        let report_path = match wiring.params.get("report") {
            None => None,
            Some(v) => Some(PathBuf::from(v.as_str().ok_or_else(|| SmokeError::Param {
                key: "report".into(),
                expected: "a path",
                found: v.to_string(),
            })?)),
        };
        Ok(Self { report_path, report: SinkReport::default() })
    }

    pub fn report(&self) -> &SinkReport {
        &self.report
    }

    fn check(input: &Input<'_, HypothesesHeader>) -> Result<(), SmokeError> {
        let frame = input.header.header().frame_id;
        for (index, found) in input.payload.iter().enumerate() {
            let expected = -value(frame, index);
            if *found != expected {
                return Err(SmokeError::Corrupted { frame, index, found: *found, expected });
            }
        }
        Ok(())
    }
}

impl Sink for CheckingSink {
    type In = HypothesesHeader;
    type Error = SmokeError;

    fn consume(&mut self, input: Input<'_, HypothesesHeader>) -> Result<(), SmokeError> {
        let frame = input.header.header().frame_id;
        let report = &mut self.report;
        report.received += 1;
        if let Some(last) = report.last_frame {
            report.gaps += frame.saturating_sub(last + 1);
        }
        report.first_frame.get_or_insert(frame);
        report.last_frame = Some(frame);
        let stamps = &input.header.header().stamps;
        if StampSlot::ALL.into_iter().any(|slot| slot != StampSlot::Source && stamps.get(slot).is_some()) {
            report.relayed += 1;
        }
        if input.header.header().has_flag(flags::UPSTREAM_RESTARTED) {
            report.restart_notices += 1;
        }
        match Self::check(&input) {
            Ok(()) => {
                report.intact += 1;
                Ok(())
            }
            Err(err) => {
                report.corrupted += 1;
                Err(err)
            }
        }
    }

    fn finish(&mut self) -> Result<(), SmokeError> {
        let json = serde_json::to_string_pretty(&self.report).expect("plain data");
        match &self.report_path {
            Some(path) => {
                std::fs::write(path, json).map_err(|source| SmokeError::Report { path: path.clone(), source })
            }
            None => {
                tracing::info!("smoke sink report: {json}");
                Ok(())
            }
        }
    }
}
