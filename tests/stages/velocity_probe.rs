//! A test stage standing in for the sampler: for every Condition handle it
//! asks the inference stage, over the graph's request-response edge, for
//! the velocities of a fixed set of poses (and once for an unknown
//! condition), and writes what came back as JSON lines to `params.report`.

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use poseflow_contracts::{ConditionHandle, VelocityRequest, VelocityResponse};
use poseflow_e2e::probe_poses;
use poseflow_runtime::{Input, Sink};
use poseflow_transport::{Node, RequestClient, create_node};

const SAMPLES: usize = 50;
const T: f32 = 0.2;

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct ProbeError(String);

struct Probe {
    // Declared before the node it was created on, so it is dropped first.
    client: RequestClient<VelocityRequest, VelocityResponse>,
    _node: Node,
    report: std::fs::File,
    requests: u64,
}

impl Probe {
    fn call(&mut self, handle: &ConditionHandle, condition_id: u64) -> Result<serde_json::Value, ProbeError> {
        self.requests += 1;
        let poses = probe_poses(handle.header.frame_id, handle.header.object_id, SAMPLES);
        let request = VelocityRequest {
            step_index: 1,
            step_count: 5,
            ..VelocityRequest::single(handle.header, condition_id, self.requests, SAMPLES as u32, T)
        };
        let reply = self
            .client
            .call(request, poses.len(), |out| out.copy_from_slice(&poses), Duration::from_secs(20))
            .map_err(|e| ProbeError(e.to_string()))?;
        let response = reply.header();
        Ok(serde_json::json!({
            "frame": handle.header.frame_id,
            "object": handle.header.object_id,
            "condition_id": condition_id,
            "request_id": response.request_id,
            "status": response.status,
            "velocities": reply.payload(),
        }))
    }
}

impl Sink for Probe {
    type In = ConditionHandle;
    type Error = ProbeError;

    fn consume(&mut self, input: Input<'_, ConditionHandle>) -> Result<(), ProbeError> {
        let handle = *input.header;
        let known = self.call(&handle, handle.condition_id)?;
        let unknown = self.call(&handle, handle.condition_id ^ (1 << 63))?;
        for line in [known, unknown] {
            writeln!(self.report, "{line}").map_err(|e| ProbeError(e.to_string()))?;
        }
        Ok(())
    }

    fn finish(&mut self) -> Result<(), ProbeError> {
        self.report.flush().map_err(|e| ProbeError(e.to_string()))
    }
}

fn main() -> std::process::ExitCode {
    poseflow_runtime::run_sink(|wiring| -> Result<_, poseflow_runtime::BuildError> {
        let report = wiring.params.get("report").and_then(|v| v.as_str()).ok_or("params.report: expected a path")?;
        let [edge] = wiring.calls.as_slice() else { return Err("expected one request-response edge it calls".into()) };
        let node = create_node(&format!("{}-client", wiring.stage))?;
        let client = RequestClient::create(&node, &edge.service, edge.max_payload_len)?;
        let report = std::fs::File::create(PathBuf::from(report)).map_err(|e| format!("{report}: {e}"))?;
        Ok(Probe { client, _node: node, report, requests: 0 })
    })
}
