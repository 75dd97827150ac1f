//! Running a stage as a process of a graph over iceoryx2.

use std::process::ExitCode;
use std::time::{Duration, Instant};

use iceoryx2::prelude::{CallbackProgression, WaitSetBuilder};
use iceoryx2::waitset::WaitSetRunResult;
use poseflow_contracts::{Heartbeat, MessageHeader, Stage, StageState};
use poseflow_graph::{EdgeWiring, OverflowPolicy, StageWiring};
use poseflow_transport::{
    EdgeOptions, EdgeSubscriber, Ipc, Node, Overflow, Publisher, create_node,
};

use crate::stage::{EmitError, Emitter, Input, Sink, Source, SourceStep, Transform};
use crate::stats::Stats;
use crate::{RuntimeError, init_logging};

/// How long a finished stage waits for its receivers to drain before exiting
/// anyway.
const END_OF_STREAM_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a stage waits at start-up for the stages reading its output.
const READERS_TIMEOUT: Duration = Duration::from_secs(10);
/// How long a stage waits for the supervisor to take its final heartbeat.
const FINAL_HEARTBEAT_TIMEOUT: Duration = Duration::from_secs(1);

/// The parts every stage process has.
struct StageProcess {
    wiring: StageWiring,
    node: Node,
    heartbeat: Publisher<Heartbeat>,
    heartbeat_period: Duration,
    stats: Stats,
}

fn edge_options(edge: &EdgeWiring) -> EdgeOptions {
    EdgeOptions {
        queue: edge.queue,
        overflow: match edge.overflow {
            OverflowPolicy::DropOldest => Overflow::DropOldest,
            OverflowPolicy::Block => Overflow::Block,
        },
        max_payload_len: edge.max_payload_len,
    }
}

/// How an event loop ended.
enum LoopEnd {
    EndOfStream,
    Terminated,
}

impl StageProcess {
    fn start(inputs: usize, outputs: usize) -> Result<Self, RuntimeError> {
        init_logging();
        let wiring = StageWiring::from_env().map_err(RuntimeError::Wiring)?;
        let expected = match (inputs, outputs) {
            (0, 1) => "no input and one output edge (a source)",
            (1, 0) => "one input and no output edge (a sink)",
            _ => "one input and one output edge",
        };
        if wiring.inputs.len() != inputs || wiring.outputs.len() != outputs {
            return Err(RuntimeError::Shape {
                stage: wiring.stage.clone(),
                expected,
                found: format!(
                    "{} input(s) and {} output(s)",
                    wiring.inputs.len(),
                    wiring.outputs.len()
                ),
            });
        }
        let node = create_node(&wiring.stage)?;
        let heartbeat = Publisher::create(
            &node,
            &wiring.heartbeat_service,
            &EdgeOptions {
                queue: 1,
                overflow: Overflow::DropOldest,
                max_payload_len: 1,
            },
        )?;
        let heartbeat_period = Duration::from_millis(wiring.heartbeat_ms);
        Ok(Self {
            wiring,
            node,
            heartbeat,
            heartbeat_period,
            stats: Stats::new(),
        })
    }

    fn input<H: MessageHeader>(&self) -> Result<EdgeSubscriber<H>, RuntimeError> {
        let edge = &self.wiring.inputs[0];
        Ok(EdgeSubscriber::create(
            &self.node,
            &edge.service,
            &edge_options(edge),
        )?)
    }

    /// The output edge, once its readers are connected (or the start-up
    /// timeout passed).
    fn output<H: MessageHeader>(&self) -> Result<Publisher<H>, RuntimeError> {
        let edge = &self.wiring.outputs[0];
        let publisher = Publisher::create(&self.node, &edge.service, &edge_options(edge))?;
        let connected = publisher.wait_for_receivers(edge.readers, READERS_TIMEOUT)?;
        if connected < edge.readers {
            tracing::warn!(edge = %edge.edge, connected, expected = edge.readers, "starting before every reader connected");
        }
        Ok(publisher)
    }

    fn beat(heartbeat: &Publisher<Heartbeat>, stats: &Stats, state: StageState) {
        if let Err(err) = heartbeat.publish(stats.heartbeat(state), 0, |_| {}) {
            tracing::warn!(%err, "heartbeat not sent");
        }
    }

    /// The last heartbeat, with the final counters. It is handed over with
    /// the end-of-stream handshake: a sample still queued when its
    /// publisher exits would be lost with it.
    fn last_beat(heartbeat: &Publisher<Heartbeat>, stats: &Stats) {
        Self::beat(heartbeat, stats, StageState::Finished);
        if let Err(err) = heartbeat.end_of_stream(FINAL_HEARTBEAT_TIMEOUT) {
            tracing::warn!(%err, "final heartbeat not acknowledged");
        }
    }

    /// Sleeps until the input or the heartbeat timer wakes it; hands every
    /// valid message to `on_input`.
    fn event_loop<H: MessageHeader>(
        &mut self,
        input: &EdgeSubscriber<H>,
        mut on_input: impl FnMut(Input<'_, H>, &mut Stats),
    ) -> Result<LoopEnd, RuntimeError> {
        let waitset = WaitSetBuilder::new()
            .create::<Ipc>()
            .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
        let input_guard = waitset
            .attach_notification(input)
            .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
        let beat_guard = waitset
            .attach_interval(self.heartbeat_period)
            .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
        let (stats, heartbeat) = (&mut self.stats, &self.heartbeat);
        Self::beat(heartbeat, stats, StageState::Running);
        let mut ended = false;
        let mut failure = None;
        let run = waitset.wait_and_process(|id| {
            if id.has_event_from(&input_guard) {
                let step = input.take_events().and_then(|end| {
                    ended |= end;
                    drain(input, stats, &mut on_input)
                });
                if let Err(err) = step {
                    failure = Some(err);
                    return CallbackProgression::Stop;
                }
                if ended {
                    return CallbackProgression::Stop;
                }
            }
            if id.has_event_from(&beat_guard) {
                Self::beat(heartbeat, stats, StageState::Running);
            }
            CallbackProgression::Continue
        });
        if let Some(err) = failure {
            return Err(err.into());
        }
        match run.map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))? {
            WaitSetRunResult::StopRequest if ended => Ok(LoopEnd::EndOfStream),
            _ => Ok(LoopEnd::Terminated),
        }
    }
}

/// Takes every queued message, rejects those that break their contract,
/// counts gaps, times the handler.
fn drain<H: MessageHeader>(
    input: &EdgeSubscriber<H>,
    stats: &mut Stats,
    on_input: &mut impl FnMut(Input<'_, H>, &mut Stats),
) -> Result<(), poseflow_transport::TransportError> {
    while let Some(message) = input.receive()? {
        let header = message.header();
        let frame = header.header().frame_id;
        if let Err(err) = header.check_payload(message.payload()) {
            stats.errors += 1;
            tracing::warn!(edge = input.name(), frame, %err, "message rejected");
            continue;
        }
        stats.frames_in += 1;
        stats.observe_frame(frame);
        let _span = tracing::debug_span!("frame", id = frame).entered();
        let started = Instant::now();
        on_input(
            Input {
                header,
                payload: message.payload(),
            },
            stats,
        );
        stats.record_latency(started.elapsed());
    }
    Ok(())
}

/// Writes outputs straight into loaned shared memory.
struct IpcEmitter<'a, H: MessageHeader> {
    publisher: &'a Publisher<H>,
    slot: Option<Stage>,
    sent: &'a mut u64,
}

impl<H: MessageHeader> Emitter<H> for IpcEmitter<'_, H> {
    fn emit(
        &mut self,
        mut header: H,
        len: usize,
        fill: &mut dyn FnMut(&mut [f32]),
    ) -> Result<(), EmitError> {
        if let Some(slot) = self.slot {
            header.header_mut().stamps.stamp(slot);
        }
        let receivers = self
            .publisher
            .publish(header, len, fill)
            .map_err(|e| EmitError(e.to_string()))?;
        tracing::trace!(receivers, "published");
        *self.sent += 1;
        Ok(())
    }
}

fn finish_output<H: MessageHeader>(output: &Publisher<H>) {
    match output.end_of_stream(END_OF_STREAM_TIMEOUT) {
        Ok(end) => tracing::info!(
            edge = output.name(),
            receivers = end.receivers,
            acknowledged = end.acknowledged,
            "end of stream"
        ),
        Err(err) => tracing::warn!(edge = output.name(), %err, "end of stream not delivered"),
    }
}

fn exit(result: Result<(), RuntimeError>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            init_logging();
            tracing::error!(%err, "stage failed");
            ExitCode::FAILURE
        }
    }
}

fn build<T>(
    wiring: &StageWiring,
    make: impl FnOnce(&StageWiring) -> Result<T, String>,
) -> Result<T, RuntimeError> {
    make(wiring).map_err(|reason| RuntimeError::Build {
        stage: wiring.stage.clone(),
        reason,
    })
}

/// Runs a [`Transform`] as a graph process; `make` builds it from the
/// stage's wiring (its `params` in particular). Call it from `main`.
pub fn run_transform<T: Transform>(
    make: impl FnOnce(&StageWiring) -> Result<T, String>,
) -> ExitCode {
    exit((|| {
        let mut process = StageProcess::start(1, 1)?;
        let mut stage = build(&process.wiring, make)?;
        let _span = tracing::info_span!("stage", name = %process.wiring.stage).entered();
        let input = process.input::<T::In>()?;
        let output = process.output::<T::Out>()?;
        tracing::info!(input = input.name(), output = output.name(), "running");
        let end = process.event_loop(&input, |message, stats| {
            let mut emitter = IpcEmitter {
                publisher: &output,
                slot: T::SLOT,
                sent: &mut stats.frames_out,
            };
            if let Err(err) = stage.process(message, &mut emitter) {
                stats.errors += 1;
                tracing::warn!(%err, "process failed; frame skipped");
            }
        })?;
        if let LoopEnd::EndOfStream = end {
            StageProcess::beat(&process.heartbeat, &process.stats, StageState::Draining);
            finish_output(&output);
            input.acknowledge_end()?;
        }
        StageProcess::last_beat(&process.heartbeat, &process.stats);
        Ok(())
    })())
}

/// Runs a [`Sink`] as a graph process.
pub fn run_sink<K: Sink>(make: impl FnOnce(&StageWiring) -> Result<K, String>) -> ExitCode {
    exit((|| {
        let mut process = StageProcess::start(1, 0)?;
        let mut sink = build(&process.wiring, make)?;
        let _span = tracing::info_span!("stage", name = %process.wiring.stage).entered();
        let input = process.input::<K::In>()?;
        tracing::info!(input = input.name(), "running");
        let end = process.event_loop(&input, |message, stats| {
            if let Err(err) = sink.consume(message) {
                stats.errors += 1;
                tracing::warn!(%err, "consume failed; frame skipped");
            }
        })?;
        if let Err(err) = sink.finish() {
            tracing::error!(%err, "sink could not finish");
        }
        if let LoopEnd::EndOfStream = end {
            input.acknowledge_end()?;
        }
        StageProcess::last_beat(&process.heartbeat, &process.stats);
        Ok(())
    })())
}

/// Runs a [`Source`] as a graph process. With a `rate_hz` parameter it emits
/// on a timer; without, as fast as its output edge accepts.
pub fn run_source<S: Source>(make: impl FnOnce(&StageWiring) -> Result<S, String>) -> ExitCode {
    exit((|| {
        let mut process = StageProcess::start(0, 1)?;
        let mut source = build(&process.wiring, make)?;
        let _span = tracing::info_span!("stage", name = %process.wiring.stage).entered();
        let output = process.output::<S::Out>()?;
        let rate_hz = process
            .wiring
            .params
            .get("rate_hz")
            .and_then(|v| v.as_f64());
        tracing::info!(output = output.name(), ?rate_hz, "running");
        let StageProcess {
            node,
            heartbeat,
            heartbeat_period,
            stats,
            ..
        } = &mut process;
        let mut step = |stats: &mut Stats| -> SourceStep {
            let mut emitter = IpcEmitter {
                publisher: &output,
                slot: S::SLOT,
                sent: &mut stats.frames_out,
            };
            let started = Instant::now();
            let result = source.next(&mut emitter);
            stats.record_latency(started.elapsed());
            result.unwrap_or_else(|err| {
                stats.errors += 1;
                tracing::warn!(%err, "source failed; frame skipped");
                SourceStep::Continue
            })
        };
        let finished = match rate_hz.filter(|hz| *hz > 0.0) {
            Some(hz) => paced(
                heartbeat,
                *heartbeat_period,
                stats,
                Duration::from_secs_f64(1.0 / hz),
                &mut step,
            )?,
            None => {
                let mut last_beat = Instant::now();
                StageProcess::beat(heartbeat, stats, StageState::Running);
                loop {
                    // Returns an error once SIGINT/SIGTERM arrived; does not sleep.
                    if node.wait(Duration::ZERO).is_err() {
                        break false;
                    }
                    if step(stats) == SourceStep::Finished {
                        break true;
                    }
                    if last_beat.elapsed() >= *heartbeat_period {
                        StageProcess::beat(heartbeat, stats, StageState::Running);
                        last_beat = Instant::now();
                    }
                }
            }
        };
        if finished {
            StageProcess::beat(heartbeat, stats, StageState::Draining);
            finish_output(&output);
        }
        StageProcess::last_beat(heartbeat, stats);
        Ok(())
    })())
}

/// The timer-driven source loop; returns whether the source finished.
fn paced(
    heartbeat: &Publisher<Heartbeat>,
    heartbeat_period: Duration,
    stats: &mut Stats,
    period: Duration,
    step: &mut impl FnMut(&mut Stats) -> SourceStep,
) -> Result<bool, RuntimeError> {
    let waitset = WaitSetBuilder::new()
        .create::<Ipc>()
        .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
    let tick = waitset
        .attach_interval(period)
        .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
    let beat = waitset
        .attach_interval(heartbeat_period)
        .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
    let mut finished = false;
    waitset
        .wait_and_process(|id| {
            if id.has_event_from(&tick) && step(stats) == SourceStep::Finished {
                finished = true;
                return CallbackProgression::Stop;
            }
            if id.has_event_from(&beat) {
                StageProcess::beat(heartbeat, stats, StageState::Running);
            }
            CallbackProgression::Continue
        })
        .map_err(|e| RuntimeError::WaitSet(format!("{e:?}")))?;
    Ok(finished)
}
