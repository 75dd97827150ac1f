//! Spawns every stage of a graph as its own process and keeps it running
//! according to its restart policy.

use std::collections::BTreeMap;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use iceoryx2::prelude::{CallbackProgression, WaitSetBuilder};
use poseflow_contracts::Heartbeat;
use poseflow_graph::{Graph, RestartPolicy, Stage, StageWiring, WIRING_ENV};
use poseflow_transport::{EdgeOptions, EdgeSubscriber, Ipc, Overflow, create_node, remove_dead_nodes};

use crate::status::{Outcome, Report, StageReport, edge_flows};
use crate::{LaunchError, LaunchOptions, LogFormat};

/// How often children are checked for exit and heartbeats are read. This is
/// the supervisor's own loop, not the data path.
const TICK: Duration = Duration::from_millis(20);
/// How long stages get to exit after SIGTERM before SIGKILL.
const STOP_GRACE: Duration = Duration::from_secs(5);

/// One supervised stage.
struct Supervised<'g> {
    stage: &'g Stage,
    wiring: StageWiring,
    heartbeats: EdgeSubscriber<Heartbeat>,
    child: Option<Child>,
    started: Instant,
    last_heartbeat_at: Instant,
    next_backoff: Duration,
    restart_at: Option<Instant>,
    died_at: Option<Instant>,
    report: StageReport,
}

impl Supervised<'_> {
    fn spawn(&mut self, log_format: LogFormat, stage_log: Option<&std::fs::File>) -> Result<(), LaunchError> {
        // Each process learns how many ran before it (see StageWiring::incarnation).
        self.wiring.incarnation = self.report.restarts;
        let mut command = Command::new(&self.stage.exe);
        command
            .args(&self.stage.args)
            .env(WIRING_ENV, self.wiring.to_json())
            .env(
                "POSEFLOW_LOG_FORMAT",
                match log_format {
                    LogFormat::Pretty => "pretty",
                    LogFormat::Json => "json",
                },
            )
            .stdin(Stdio::null());
        match stage_log {
            Some(file) => {
                let copy = |file: &std::fs::File| {
                    file.try_clone().map_err(|source| LaunchError::Spawn {
                        stage: self.stage.name.clone(),
                        exe: self.stage.exe.clone(),
                        source,
                    })
                };
                command.stdout(copy(file)?).stderr(copy(file)?);
            }
            // Stage output joins the launcher's logs; its stdout is reserved
            // for `--json`.
            None => {
                command.stdout(std::io::stderr());
            }
        }
        // SAFETY: prctl is async-signal-safe; it only asks the kernel to send
        // SIGTERM to the child if this supervisor dies, so no stage outlives it.
        unsafe {
            use std::os::unix::process::CommandExt;
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
        let child = command.spawn().map_err(|source| LaunchError::Spawn {
            stage: self.stage.name.clone(),
            exe: self.stage.exe.clone(),
            source,
        })?;
        tracing::info!(stage = %self.stage.name, pid = child.id(), "started");
        self.report.pid = child.id();
        self.child = Some(child);
        self.started = Instant::now();
        self.last_heartbeat_at = self.started;
        self.report.outcome = Outcome::Running;
        if let Some(died) = self.died_at.take() {
            self.report.restart_latency_ms.push(died.elapsed().as_secs_f64() * 1e3);
        }
        Ok(())
    }

    fn read_heartbeats(&mut self) {
        // Events first: a final heartbeat is announced by end-of-stream, and
        // everything sent before it is already queued.
        let ended = self.heartbeats.take_events().unwrap_or(false);
        loop {
            match self.heartbeats.receive() {
                Ok(Some(beat)) => {
                    self.report.beat(*beat.header());
                    self.last_heartbeat_at = Instant::now();
                }
                Ok(None) => break,
                Err(err) => {
                    tracing::debug!(stage = %self.stage.name, %err, "heartbeat receive failed");
                    break;
                }
            }
        }
        if ended && let Err(err) = self.heartbeats.acknowledge_end() {
            tracing::debug!(stage = %self.stage.name, %err, "final heartbeat not acknowledged");
        }
    }

    /// Handles an exited child according to the restart policy.
    fn on_exit(&mut self, status: std::process::ExitStatus) {
        self.child = None;
        let now = Instant::now();
        let success = status.success();
        let restart = match self.stage.restart.policy {
            RestartPolicy::Never => false,
            RestartPolicy::OnFailure => !success,
            RestartPolicy::Always => true,
        };
        tracing::info!(stage = %self.stage.name, %status, "exited");
        if !restart {
            self.report.outcome =
                if success { Outcome::Finished } else { Outcome::Failed(format!("exited with {status}")) };
            return;
        }
        if self.report.restarts >= self.stage.restart.max_restarts {
            self.report.outcome =
                Outcome::Failed(format!("exited with {status} after {} restarts (max_restarts)", self.report.restarts));
            return;
        }
        self.report.outcome = Outcome::Restarting;
        self.died_at = Some(now);
        self.restart_at = Some(now + self.next_backoff);
        tracing::warn!(stage = %self.stage.name, %status, backoff_ms = self.next_backoff.as_millis() as u64, "will restart");
        self.next_backoff = (self.next_backoff * 2).min(self.stage.restart.max_backoff);
    }

    /// Why the stage counts as hung, if it does: frozen (its heartbeats
    /// stopped), never started beating, or stuck in its own code. Time spent
    /// waiting on a full downstream queue does not count.
    fn hung(&self, now: Instant, graph: &Graph) -> Option<&'static str> {
        let silent = now.duration_since(self.last_heartbeat_at);
        let Some(beat) = self.report.heartbeat.filter(|b| b.pid == self.report.pid) else {
            return (silent > graph.heartbeat_timeout)
                .then_some("no first heartbeat within graph.heartbeat_timeout_ms");
        };
        if silent > graph.silence_timeout {
            return Some("heartbeats stopped for longer than graph.silence_timeout_ms (process frozen or stopped)");
        }
        (u128::from(beat.busy_us) > graph.heartbeat_timeout.as_micros())
            .then_some("busy in one message longer than graph.heartbeat_timeout_ms")
    }

    fn kill(&mut self, signal: i32) {
        if let Some(child) = &self.child {
            // SAFETY: sending a signal to our own child's pid.
            unsafe { libc::kill(child.id() as i32, signal) };
        }
    }
}

/// Runs the graph until every stage has finished, a stage fails beyond its
/// restart policy, or SIGINT/SIGTERM arrives.
pub fn supervise(graph: &Graph, options: &LaunchOptions) -> Result<Report, LaunchError> {
    let removed = remove_dead_nodes()?;
    if removed > 0 {
        tracing::info!(removed, "cleaned up resources of dead processes from earlier runs");
    }
    let node = create_node("poseflow-supervisor")?;
    let mut stages = Vec::new();
    let recorded: &[String] = options.record.as_ref().map_or(&[], |(_, edges)| edges);
    // Before any stage starts, so the first messages are recorded too.
    let recorder = match &options.record {
        Some((path, edges)) => Some(crate::record::Recorder::start(graph, &options.instance, edges, path.clone())?),
        None => None,
    };
    let host = options.host.as_deref();
    // A host whose edges cross to other hosts runs the bridge that carries them.
    let bridge = match host {
        Some(host) => graph.bridge(host, &options.instance)?,
        None => None,
    };
    let placed = graph.stages_on(host).map(|stage| Ok((stage, graph.wiring_on(stage, &options.instance, host)?)));
    let bridged = bridge.iter().map(|(stage, wiring)| Ok((stage, wiring.clone())));
    for placed in placed.chain(bridged) {
        let (stage, mut wiring): (&Stage, StageWiring) = placed.map_err(LaunchError::Graph)?;
        // The recorder is one more reader for publishers to wait for.
        for output in &mut wiring.outputs {
            if recorded.contains(&output.edge) {
                output.readers += 1;
            }
        }
        let heartbeats = EdgeSubscriber::create(
            &node,
            &wiring.heartbeat_service,
            &EdgeOptions { queue: 1, overflow: Overflow::DropOldest, max_payload_len: 1 },
        )?;
        stages.push(Supervised {
            stage,
            wiring,
            heartbeats,
            child: None,
            started: Instant::now(),
            last_heartbeat_at: Instant::now(),
            next_backoff: stage.restart.backoff,
            restart_at: None,
            died_at: None,
            report: StageReport::new(&stage.name),
        });
    }
    let stage_log = match &options.stage_log {
        Some(path) => Some(
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .map_err(|source| LaunchError::StageLog { path: path.clone(), source })?,
        ),
        None => None,
    };
    let started = Instant::now();
    for s in &mut stages {
        s.spawn(options.log_format, stage_log.as_ref())?;
    }
    tracing::info!(graph = %graph.name, instance = %options.instance, host, stages = stages.len(), "graph running");

    let waitset = WaitSetBuilder::new().create::<Ipc>().map_err(|e| LaunchError::WaitSet(Box::new(e)))?;
    let tick = waitset.attach_interval(TICK).map_err(|e| LaunchError::WaitSet(Box::new(e)))?;
    let mut last_status = Instant::now();
    let mut failure: Option<LaunchError> = None;
    waitset
        .wait_and_process(|id| {
            if !id.has_event_from(&tick) {
                return CallbackProgression::Continue;
            }
            if let Err(err) = step(&mut stages, graph, options, stage_log.as_ref()) {
                failure = Some(err);
                return CallbackProgression::Stop;
            }
            if let Some(every) = options.status_every
                && last_status.elapsed() >= every
            {
                let reports = stages.iter().map(|s| &s.report);
                eprintln!("{}", crate::status::status_lines(&options.instance, started.elapsed(), reports));
                last_status = Instant::now();
            }
            let all_finished = stages.iter().all(|s| s.report.outcome == Outcome::Finished);
            let any_failed = stages.iter().any(|s| matches!(s.report.outcome, Outcome::Failed(_)));
            if all_finished || any_failed { CallbackProgression::Stop } else { CallbackProgression::Continue }
        })
        .map_err(|e| LaunchError::WaitSet(Box::new(e)))?;
    stop_all(&mut stages);
    let recording = recorder.map(|r| r.finish()).transpose()?;
    if let Some(err) = failure {
        return Err(err);
    }
    let removed = remove_dead_nodes()?;
    let stages = stages.into_iter().map(|s| (s.stage.name.clone(), s.report)).collect::<BTreeMap<_, _>>();
    Ok(Report {
        graph: graph.name.clone(),
        instance: options.instance.clone(),
        elapsed: started.elapsed(),
        stale_nodes_removed_at_exit: removed,
        recording,
        edges: edge_flows(graph, &stages),
        stages,
    })
}

/// One supervisor tick: read heartbeats, reap exits, restart, detect hangs.
fn step(
    stages: &mut [Supervised<'_>],
    graph: &Graph,
    options: &LaunchOptions,
    stage_log: Option<&std::fs::File>,
) -> Result<(), LaunchError> {
    let now = Instant::now();
    for s in stages.iter_mut() {
        s.read_heartbeats();
        if let Some(child) = &mut s.child {
            let exited =
                child.try_wait().map_err(|source| LaunchError::Wait { stage: s.stage.name.clone(), source })?;
            if let Some(status) = exited {
                s.on_exit(status);
            } else if let Some(reason) = s.hung(now, graph) {
                tracing::error!(stage = %s.stage.name, reason, "stage hung; killing it");
                s.report.hangs += 1;
                s.kill(libc::SIGKILL);
            }
        }
        if s.restart_at.is_some_and(|at| now >= at) {
            s.restart_at = None;
            // The dead process's ports still occupy its services until removed.
            remove_dead_nodes()?;
            s.report.restarts += 1;
            s.spawn(options.log_format, stage_log)?;
        }
    }
    Ok(())
}

/// SIGTERM to every running stage, SIGKILL to those still alive after the
/// grace period, then removal of whatever the killed ones left behind.
fn stop_all(stages: &mut [Supervised<'_>]) {
    for s in stages.iter_mut() {
        s.restart_at = None;
        s.kill(libc::SIGTERM);
    }
    let deadline = Instant::now() + STOP_GRACE;
    for s in stages.iter_mut() {
        while let Some(child) = &mut s.child {
            match child.try_wait() {
                Ok(Some(status)) => {
                    tracing::info!(stage = %s.stage.name, %status, "stopped");
                    if s.report.outcome == Outcome::Running {
                        s.report.outcome = Outcome::Stopped;
                    }
                    s.child = None;
                }
                Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(10)),
                _ => {
                    tracing::warn!(stage = %s.stage.name, "did not stop after SIGTERM; killing");
                    s.kill(libc::SIGKILL);
                    s.report.killed_at_stop = true;
                    if let Some(mut child) = s.child.take() {
                        let _ = child.wait();
                    }
                    s.report.outcome = Outcome::Stopped;
                }
            }
        }
    }
}
