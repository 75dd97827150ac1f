//! The selector stage process: `exe = "selector"` in a graph file;
//! Hypotheses in, Estimate out, and — for the model-based methods and
//! refinement — the Observations as a side input (`side_inputs`).

use std::process::ExitCode;

use poseflow_graph::StageWiring;
use poseflow_runtime::BuildError;
use poseflow_selector::SelectorParams;
use poseflow_selector::stage::SelectorStage;

fn make(wiring: &StageWiring) -> Result<SelectorStage, BuildError> {
    let params = SelectorParams::from_json(&wiring.params)?;
    if params.needs_models() && wiring.side_inputs.is_empty() {
        return Err(format!(
            "stage `{}`: method {:?}{} scores the observed points: list the Observation edge in `side_inputs`",
            wiring.stage,
            params.method,
            if params.refine { " with refine" } else { "" }
        )
        .into());
    }
    let stage = SelectorStage::new(params)?;
    tracing::info!(method = ?stage.params().method, refine = stage.params().refine, "selector ready");
    Ok(stage)
}

fn main() -> ExitCode {
    poseflow_runtime::run_transform_or_joined(make)
}
