//! `poseflow run`: launch a graph file as supervised processes.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;

use poseflow_launch::{LaunchOptions, LogFormat};

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Graph file to launch (see deploy/*.toml).
    #[arg(long)]
    pub graph: PathBuf,

    /// Name of this graph instance: the namespace of its shared-memory
    /// services, so two instances can run side by side. Default: the graph's
    /// name followed by this process id.
    #[arg(long)]
    pub instance: Option<String>,

    /// Directories searched for stage executables given by bare name, before
    /// POSEFLOW_STAGE_PATH, the directory of `poseflow` itself, and PATH.
    #[arg(long = "stage-path", value_name = "DIR")]
    pub stage_path: Vec<PathBuf>,

    /// Print a status line per stage this often (milliseconds; 0 = never).
    #[arg(long, default_value_t = 1000)]
    pub status_ms: u64,

    /// Run the stages as threads of this process, connected by in-memory
    /// queues instead of shared memory: the baseline of the latency
    /// benchmarks. The stages are built by the stage registry.
    #[arg(long)]
    pub in_process: bool,

    /// Record the messages of the graph's edges, with the time they were
    /// received, to FILE (replay them with the `replay-source` stage).
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,

    /// Edges to record (comma-separated); default: every publish-subscribe
    /// edge.
    #[arg(long, value_delimiter = ',', requires = "record")]
    pub record_edges: Vec<String>,

    /// Change one stage parameter for this run, e.g. `--set
    /// frames.frames_per_scene=5000` or `--set sampler.tracking.enabled=false`
    /// (a TOML value; anything else is a string). Repeatable.
    #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
    pub set: Vec<String>,

    /// Run only the stages the graph places on host NAME (`[hosts.NAME]`),
    /// with the Zenoh bridge that carries the edges crossing to and from
    /// the other hosts. Start the same graph file with `--host` once on
    /// each host. Without it, every stage runs here.
    #[arg(long, value_name = "NAME")]
    pub host: Option<String>,

    /// Validate the graph file and exit without starting anything.
    #[arg(long)]
    pub check: bool,

    /// Print a final JSON summary (per stage: restarts, exit status, counters,
    /// latency) on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: RunArgs, log_format: LogFormat) -> anyhow::Result<ExitCode> {
    let mut graph = poseflow_graph::load(&args.graph, &poseflow_launch::search_path(&args.stage_path))?;
    for assignment in &args.set {
        graph.set_param(assignment)?;
    }
    let instance = args.instance.clone().unwrap_or_else(|| poseflow_launch::default_instance(&graph));
    poseflow_transport::validate_name("graph instance", &instance).context("--instance")?;
    if args.check {
        let owners = poseflow_launch::stamp_owners(&graph, &poseflow_stages::registry())?;
        let stamps: Vec<String> = owners.iter().map(|(slot, stage)| format!("{}={stage}", slot.name())).collect();
        println!(
            "{}: valid graph `{}` with {} stages and {} edges; timestamp slots: {}",
            args.graph.display(),
            graph.name,
            graph.stages.len(),
            graph.edges.len(),
            stamps.join(", ")
        );
        for host in graph.hosts.keys() {
            let stages: Vec<&str> = graph.stages_on(Some(host)).map(|s| s.name.as_str()).collect();
            println!(
                "host {host}: stages {}; sends {:?}; receives {:?}",
                stages.join(", "),
                graph.sent_from(host),
                graph.received_on(host)
            );
        }
        return Ok(ExitCode::SUCCESS);
    }
    let record = match &args.record {
        Some(path) => {
            let mut edges = poseflow_launch::chosen_edges(&graph, &args.record_edges)?;
            // By default a host records the edges it has.
            if let Some(host) = args.host.as_deref().filter(|_| args.record_edges.is_empty()) {
                let here = graph.edges_on(host);
                edges.retain(|edge| here.contains(&edge.as_str()));
            }
            Some((path.clone(), edges))
        }
        None => None,
    };
    let options = LaunchOptions {
        record,
        instance,
        status_every: (args.status_ms > 0).then(|| std::time::Duration::from_millis(args.status_ms)),
        log_format,
        stage_log: None,
        in_process: args.in_process,
        host: args.host.clone(),
    };
    let report = poseflow_launch::launch(&graph, &options, &poseflow_stages::registry())?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report.to_json())?);
    } else {
        eprintln!("{}", report.table());
    }
    Ok(if report.failed() { ExitCode::FAILURE } else { ExitCode::SUCCESS })
}
