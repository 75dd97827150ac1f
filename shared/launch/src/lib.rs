//! Launches a graph file's stages and reports what they did.
//!
//! [`launch`] runs a [`Graph`] either as supervised processes (one per
//! stage, restarted by policy, killed when hung, optionally recorded) or,
//! with [`LaunchOptions::in_process`], as threads of the calling process
//! built through the stage [`Registry`]. Either way it returns a [`Report`]
//! with each stage's outcome, restarts and counters. `poseflow run`, the
//! demo, the evaluation and the benchmarks all launch graphs through here.
//!
//! [`DrivenGraph`] runs the stages between two edges of a graph in-process
//! and hands them one message at a time: the simulations, the
//! next-best-view planner and the in-process benchmark baseline estimate
//! through it.

mod driven;
mod error;
mod local;
mod record;
mod stamps;
mod status;
mod supervisor;

use std::path::PathBuf;
use std::time::Duration;

pub use driven::{DrivenGraph, stages_between};
pub use error::LaunchError;
use poseflow_graph::Graph;
use poseflow_runtime::Registry;
pub use record::chosen_edges;
pub use stamps::stamp_owners;
pub use status::{Counters, EdgeFlow, Outcome, Report, StageReport};

/// How stage processes write their logs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    #[default]
    Pretty,
    /// One JSON object per line, for log collectors.
    Json,
}

/// Everything about a launch that is not in the graph file.
#[derive(Debug, Clone, Default)]
pub struct LaunchOptions {
    /// The namespace of the graph's shared-memory services, so two
    /// instances can run side by side (see [`default_instance`]).
    pub instance: String,
    /// Record these edges' messages to this file.
    pub record: Option<(PathBuf, Vec<String>)>,
    /// Print a status line per stage this often.
    pub status_every: Option<Duration>,
    pub log_format: LogFormat,
    /// Stage processes' stdout and stderr are appended to this file instead
    /// of going to the launcher's stderr.
    pub stage_log: Option<PathBuf>,
    /// Threads of this process instead of processes.
    pub in_process: bool,
    /// Run only this host's stages (and its Zenoh bridge) of a graph that
    /// names hosts; `None`: every stage here.
    pub host: Option<String>,
}

/// The instance name `poseflow run` uses unless told otherwise: the graph's
/// name followed by this process id.
pub fn default_instance(graph: &Graph) -> String {
    format!("{}-{}", graph.name, std::process::id())
}

/// Where bare executable names are looked up, in order: `stage_path`
/// (`--stage-path`), POSEFLOW_STAGE_PATH, the running executable's own
/// directory.
pub fn search_path(stage_path: &[PathBuf]) -> Vec<PathBuf> {
    let mut dirs = stage_path.to_vec();
    if let Some(env) = std::env::var_os("POSEFLOW_STAGE_PATH") {
        dirs.extend(std::env::split_paths(&env));
    }
    if let Some(own_dir) = std::env::current_exe().ok().and_then(|p| p.parent().map(PathBuf::from)) {
        dirs.push(own_dir);
    }
    dirs
}

/// Runs `graph` until every stage has finished, a stage fails beyond its
/// restart policy, or SIGINT/SIGTERM arrives. `registry` builds the stages
/// of an in-process run; processes are started from their executables.
pub fn launch(graph: &Graph, options: &LaunchOptions, registry: &Registry) -> Result<Report, LaunchError> {
    poseflow_transport::validate_name("graph instance", &options.instance)?;
    stamp_owners(graph, registry)?;
    if let Some(host) = &options.host {
        check_host(graph, host, options)?;
    }
    if options.in_process {
        local::run(graph, &options.instance, registry, options.record.as_ref())
    } else {
        supervisor::supervise(graph, options)
    }
}

/// Checks `--host host` against the graph and the other options.
fn check_host(graph: &Graph, host: &str, options: &LaunchOptions) -> Result<(), LaunchError> {
    if !graph.hosts.contains_key(host) {
        return Err(LaunchError::UnknownHost {
            file: graph.file.clone(),
            host: host.to_string(),
            hosts: graph.hosts.keys().cloned().collect(),
        });
    }
    if options.in_process {
        return Err(LaunchError::HostInProcess);
    }
    let here = graph.edges_on(host);
    for edge in options.record.iter().flat_map(|(_, edges)| edges) {
        if !here.contains(&edge.as_str()) {
            return Err(LaunchError::RecordElsewhere { edge: edge.clone(), host: host.to_string() });
        }
    }
    Ok(())
}

/// [`launch`] for a program that launches a graph as one step of its own
/// work (the demo, an evaluation, a benchmark): the launcher's log and the
/// stages' output go to `log` (created afresh), not to the caller's
/// terminal, and `waiting` is called about four times a second until the
/// graph has ended (to draw progress).
pub fn launch_quietly(
    graph: &Graph,
    options: &LaunchOptions,
    registry: &Registry,
    log: &std::path::Path,
    mut waiting: impl FnMut(),
) -> Result<Report, LaunchError> {
    let file =
        std::fs::File::create(log).map_err(|source| LaunchError::StageLog { path: log.to_path_buf(), source })?;
    let options = LaunchOptions { stage_log: Some(log.to_path_buf()), ..options.clone() };
    let subscriber = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_ansi(false)
        .with_writer(std::sync::Mutex::new(file))
        .finish();
    std::thread::scope(|scope| {
        let launcher =
            scope.spawn(|| tracing::subscriber::with_default(subscriber, || launch(graph, &options, registry)));
        while !launcher.is_finished() {
            waiting();
            std::thread::sleep(Duration::from_millis(250));
        }
        launcher.join().unwrap_or(Err(LaunchError::LauncherPanicked))
    })
}
