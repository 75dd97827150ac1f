//! A complete stage in one file: passes on the Estimates whose rotation
//! spread is at most `max_spread_deg`, so a robot acting on the output
//! only ever sees confident poses. docs/new-stage.md walks through it.
//!
//! Build: `cargo build --release -p poseflow-stages --example confident-estimates`;
//! name `target/release/examples/confident-estimates` as a stage's `exe`.

use poseflow_contracts::{EstimateHeader, StampSlot};
use poseflow_graph::StageWiring;
use poseflow_runtime::{EmitError, Emitter, Input, Registration, Transform, run_registered};

/// Why the stage cannot start or pass a message on.
#[derive(Debug, thiserror::Error)]
enum GateError {
    #[error("param `max_spread_deg`: expected a number of degrees ≥ 0, found {0}")]
    Param(String),
    #[error(transparent)]
    Emit(#[from] EmitError),
}

/// The stage: its parameters, read once.
struct ConfidentEstimates {
    /// The largest spread passed on: √(tr Σ_R / 3), in radians.
    max_spread_rad: f32,
}

impl ConfidentEstimates {
    /// Builds the stage from its graph entry (`params` there override the
    /// default of 10°).
    fn from_wiring(wiring: &StageWiring) -> Result<Self, GateError> {
        let degrees = match wiring.params.get("max_spread_deg") {
            None => 10.0,
            Some(value) => value.as_f64().filter(|d| *d >= 0.0).ok_or_else(|| GateError::Param(value.to_string()))?,
        };
        Ok(Self { max_spread_rad: degrees.to_radians() as f32 })
    }

    /// The rotation spread of an Estimate: the root mean square angle of
    /// its kept hypotheses about their mean, per axis (radians).
    fn spread_rad(estimate: &EstimateHeader) -> f32 {
        (estimate.rotation_trace.max(0.0) / 3.0).sqrt()
    }
}

impl Transform for ConfidentEstimates {
    type In = EstimateHeader;
    type Out = EstimateHeader;
    type Error = GateError;
    /// It stamps no timestamp slot: the Estimate keeps the selector's.
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, EstimateHeader>,
        output: &mut dyn Emitter<EstimateHeader>,
    ) -> Result<(), GateError> {
        if Self::spread_rad(input.header) > self.max_spread_rad {
            tracing::debug!(frame = input.header.header.frame_id, "estimate too unsure; not passed on");
            return Ok(());
        }
        let payload = input.payload;
        Ok(output.emit(*input.header, payload.len(), &mut |out| out.copy_from_slice(payload))?)
    }
}

/// The stage's registration: its executable name, its kind and how it is
/// built. A registry holding it runs the stage in-process too.
fn registrations() -> Vec<Registration> {
    vec![Registration::transform("confident-estimates", ConfidentEstimates::from_wiring)]
}

fn main() -> std::process::ExitCode {
    run_registered(registrations(), "confident-estimates")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Collects what the stage emits.
    #[derive(Default)]
    struct Collected(Vec<(EstimateHeader, Vec<f32>)>);

    impl Emitter<EstimateHeader> for Collected {
        fn emit(
            &mut self,
            header: EstimateHeader,
            len: usize,
            fill: &mut dyn FnMut(&mut [f32]),
        ) -> Result<(), EmitError> {
            let mut payload = vec![0.0; len];
            fill(&mut payload);
            self.0.push((header, payload));
            Ok(())
        }
    }

    fn wiring(params: serde_json::Value) -> StageWiring {
        StageWiring { stage: "gate".into(), params, ..Default::default() }
    }

    /// tr Σ_R = 3 σ², so a trace of 3·(5°)² is a 5° spread.
    fn estimate(spread_deg: f32) -> EstimateHeader {
        EstimateHeader { rotation_trace: 3.0 * spread_deg.to_radians().powi(2), ..Default::default() }
    }

    #[test]
    fn passes_confident_estimates_unchanged_and_holds_back_unsure_ones() {
        let mut stage = ConfidentEstimates::from_wiring(&wiring(serde_json::json!({"max_spread_deg": 8.0}))).unwrap();
        let mut out = Collected::default();
        for (spread, payload) in [(5.0, vec![1.0, 2.0]), (30.0, vec![3.0]), (7.9, vec![4.0])] {
            let header = estimate(spread);
            stage.process(Input { header: &header, payload: &payload }, &mut out).unwrap();
        }
        let passed: Vec<Vec<f32>> = out.0.into_iter().map(|(_, payload)| payload).collect();
        assert_eq!(passed, [vec![1.0, 2.0], vec![4.0]]);
    }

    #[test]
    fn a_bad_threshold_is_named() {
        let err = ConfidentEstimates::from_wiring(&wiring(serde_json::json!({"max_spread_deg": "ten"}))).err().unwrap();
        assert_eq!(err.to_string(), "param `max_spread_deg`: expected a number of degrees ≥ 0, found \"ten\"");
        assert!(ConfidentEstimates::from_wiring(&wiring(serde_json::json!({}))).is_ok());
    }
}
