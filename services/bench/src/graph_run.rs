//! A graph run by a benchmark, with one edge recorded and its log kept in a
//! scratch directory: launched from this process, or (for the soak, which
//! kills and measures processes) `poseflow run` as a child process whose
//! JSON summary is read at the end.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use anyhow::Context;
use clap::Args;

/// The options of every benchmark that runs graphs through `poseflow run`.
#[derive(Debug, Args)]
pub struct GraphRunOptions {
    /// Stage parameters for the runs, passed to `poseflow run --set`, e.g.
    /// `frames.frames_per_scene=100000` (repeatable).
    #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
    pub set: Vec<String>,

    /// Directories searched for stage executables (as `poseflow run`).
    #[arg(long = "stage-path", value_name = "DIR")]
    pub stage_path: Vec<PathBuf>,

    /// Keep the recordings and the runs' logs here (default: a temporary
    /// directory removed at the end).
    #[arg(long)]
    pub out: Option<PathBuf>,

    /// Print the report as JSON on stdout.
    #[arg(long)]
    pub json: bool,
}

/// What to run: the graph, its instance name, `--set` overrides, where
/// stage executables are, and the edge to record into which file.
#[derive(Debug)]
pub(super) struct GraphRun<'a> {
    pub graph: &'a Path,
    pub instance: String,
    pub set: &'a [String],
    pub stage_path: &'a [PathBuf],
    /// (recording file, edge)
    pub record: (&'a Path, &'a str),
}

impl GraphRun<'_> {
    /// Launches the graph from this process and waits for its end; returns
    /// the launch report as `poseflow run --json` prints it.
    pub fn launch(&self, log: &Path) -> anyhow::Result<serde_json::Value> {
        let mut graph = poseflow_graph::load(self.graph, &poseflow_launch::search_path(self.stage_path))?;
        for assignment in self.set {
            graph.set_param(assignment)?;
        }
        let options = poseflow_launch::LaunchOptions {
            instance: self.instance.clone(),
            record: Some((self.record.0.to_path_buf(), vec![self.record.1.to_string()])),
            ..Default::default()
        };
        let report = poseflow_launch::launch_quietly(&graph, &options, &poseflow_stages::registry(), log, || {})
            .with_context(|| format!("{}: its log: {}", self.graph.display(), log.display()))?;
        Ok(report.to_json())
    }

    /// Starts `poseflow run --json` with stdout piped (the summary) and
    /// stderr into `log`.
    pub fn start(&self, log: &Path) -> anyhow::Result<Child> {
        let exe = std::env::current_exe().context("locating the poseflow executable")?;
        let log_file = std::fs::File::create(log).with_context(|| format!("{}: cannot create", log.display()))?;
        let mut command = Command::new(exe);
        command
            .arg("run")
            .arg("--graph")
            .arg(self.graph)
            .args(["--json", "--status-ms", "0", "--instance", &self.instance])
            .arg("--record")
            .arg(self.record.0)
            .arg("--record-edges")
            .arg(self.record.1);
        for assignment in self.set {
            command.arg("--set").arg(assignment);
        }
        for dir in self.stage_path {
            command.arg("--stage-path").arg(dir);
        }
        command.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(log_file);
        command.spawn().context("starting `poseflow run`")
    }
}

/// Waits for a run started by [`GraphRun::start`] and parses its summary.
pub(super) fn run_summary(child: Child, log: &Path) -> anyhow::Result<serde_json::Value> {
    let output = child.wait_with_output().context("waiting for `poseflow run`")?;
    serde_json::from_slice(&output.stdout).with_context(|| {
        format!("`poseflow run` printed no JSON summary ({}); its log: {}", output.status, log.display())
    })
}

/// A benchmark's working directory: `--out`, or a temporary one removed at
/// the end.
pub(super) struct Scratch {
    pub dir: PathBuf,
    temporary: bool,
}

impl Scratch {
    pub fn new(out: Option<&Path>, name: &str) -> anyhow::Result<Self> {
        let (dir, temporary) = match out {
            Some(dir) => (dir.to_path_buf(), false),
            None => (std::env::temp_dir().join(format!("poseflow-{name}-{}", std::process::id())), true),
        };
        std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
        Ok(Self { dir, temporary })
    }

    pub fn finish(self) {
        if self.temporary {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}
