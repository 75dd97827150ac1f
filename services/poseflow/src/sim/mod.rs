//! `poseflow sim`: closed-loop simulations on rendered scenes, with the
//! real pose stages run in-process ([`crate::pipeline`]).

mod grasp;
mod mug;

use clap::{Args, Subcommand};

#[derive(Debug, Args)]
pub struct SimArgs {
    #[command(subcommand)]
    pub command: SimCommand,
}

#[derive(Debug, Subcommand)]
pub enum SimCommand {
    /// Grasp a mug with its handle visible or hidden: single pose hypothesis vs the marginalised grasp flow.
    Grasp(grasp::GraspSimArgs),
}

pub fn run(args: &SimArgs) -> anyhow::Result<()> {
    match &args.command {
        SimCommand::Grasp(args) => grasp::run(args),
    }
}
