//! The sampler stage process: `exe = "sampler"` in a graph file; Condition
//! handles in, Hypotheses out, velocities asked of the inference stage over
//! the request-response edge in `calls`; in tracking mode the selector's
//! Estimates come back as a side input (`side_inputs`).

use std::process::ExitCode;
use std::time::Duration;

use poseflow_graph::StageWiring;
use poseflow_runtime::BuildError;
use poseflow_sampler::SamplerParams;
use poseflow_sampler::stage::{RemoteField, SamplerStage};
use poseflow_transport::{RequestClient, create_node};

fn make(wiring: &StageWiring) -> Result<SamplerStage<RemoteField>, BuildError> {
    let params = SamplerParams::from_json(&wiring.params)?;
    let [edge] = wiring.calls.as_slice() else {
        return Err(format!(
            "stage `{}`: expected exactly one request-response edge in `calls` (the inference stage's velocities), found {}",
            wiring.stage,
            wiring.calls.len()
        )
        .into());
    };
    let node = create_node(&format!("{}-velocity", wiring.stage))?;
    let client = RequestClient::create(&node, &edge.service, edge.max_payload_len)?;
    let timeout = Duration::from_millis(params.velocity_timeout_ms);
    tracing::info!(samples = params.samples, steps = params.steps, tracking = params.tracking.enabled, "sampler ready");
    Ok(SamplerStage::new(params, RemoteField::new(node, client, timeout)))
}

fn main() -> ExitCode {
    // With the selector's Estimates as a side input it can track.
    poseflow_runtime::run_transform_or_joined(make)
}
