use std::process::ExitCode;

use poseflow_contracts::{MessageHeader, MessageVisitor, visit_message};
use poseflow_graph::StageWiring;
use poseflow_replay::ReplaySource;

/// Runs the replay with the header type of the output edge.
struct Replay;

impl MessageVisitor for Replay {
    type Output = ExitCode;
    fn visit<H: MessageHeader + Send + 'static>(self) -> ExitCode {
        poseflow_runtime::run_source(ReplaySource::<H>::from_wiring)
    }
}

fn main() -> ExitCode {
    poseflow_runtime::init_logging();
    let message = match StageWiring::from_env() {
        Ok(wiring) => wiring.outputs.first().map(|o| o.message.clone()).unwrap_or_default(),
        Err(err) => {
            tracing::error!("{err}");
            return ExitCode::FAILURE;
        }
    };
    visit_message(&message, Replay).unwrap_or_else(|| {
        tracing::error!("replay-source: the output edge must be one publish-subscribe edge with a known message type, got {message:?}");
        ExitCode::FAILURE
    })
}
