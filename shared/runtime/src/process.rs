//! Running a stage as a process of a graph over iceoryx2.

use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use iceoryx2::prelude::{CallbackProgression, SynchronousMultiplexing, WaitSetBuilder};
use iceoryx2::waitset::WaitSetRunResult;
use poseflow_contracts::{MessageHeader, StageState, StampSlot, flags};
use poseflow_graph::StageWiring;
use poseflow_transport::{EdgeSubscriber, Ipc, Node, Publisher, RequestServer, Responder, TransportError, create_node};

use crate::error::error_chain;
use crate::heartbeat::HeartbeatThread;
use crate::liveness::Liveness;
use crate::stage::{EmitError, Emitter, Flush, Input, Joined, Server, Sink, Source, SourceStep, Transform};
use crate::{BuildError, RuntimeError, init_logging};

/// How long a finished stage waits for its receivers to drain before exiting
/// anyway.
const END_OF_STREAM_TIMEOUT: Duration = Duration::from_secs(30);
/// How often an event loop looks at its input queue without being woken.
const LOST_WAKEUP_CHECK: Duration = Duration::from_secs(1);
/// How often a stage waiting at start-up for the stages reading its output
/// says so (it waits until they connect or it is stopped).
const READERS_WARN_EVERY: Duration = Duration::from_secs(10);

fn waitset_error(err: impl std::error::Error + Send + Sync + 'static) -> RuntimeError {
    RuntimeError::WaitSet(Box::new(err))
}

/// The parts every stage process has.
struct StageProcess {
    wiring: StageWiring,
    node: Node,
    liveness: Arc<Liveness>,
    heartbeat: HeartbeatThread,
}

/// Something else an event loop wakes on (a request server, a side input),
/// and what it does then.
struct Attachment<'a, X> {
    source: &'a X,
    on_event: &'a mut dyn FnMut() -> Result<(), TransportError>,
}

/// How an event loop ended.
enum LoopEnd {
    EndOfStream,
    Terminated,
}

impl StageProcess {
    fn start(inputs: usize, outputs: usize) -> Result<Self, RuntimeError> {
        init_logging();
        let wiring = StageWiring::from_env()?;
        let expected = match (inputs, outputs) {
            (0, 1) => "no input and one output edge (a source)",
            (1, 0) => "one input and no output edge (a sink)",
            _ => "one input and one output edge",
        };
        if wiring.inputs.len() != inputs || wiring.outputs.len() != outputs {
            return Err(RuntimeError::Shape {
                stage: wiring.stage.clone(),
                expected,
                found: format!("{} input(s) and {} output(s)", wiring.inputs.len(), wiring.outputs.len()),
            });
        }
        let node = create_node(&wiring.stage)?;
        let liveness = Arc::new(Liveness::new());
        if wiring.incarnation > 0 {
            tracing::info!(stage = %wiring.stage, incarnation = wiring.incarnation, "restarted; the first output says so");
            liveness.restarted();
        }
        let period = Duration::from_millis(wiring.heartbeat_ms);
        let heartbeat = HeartbeatThread::spawn(&wiring.stage, &wiring.heartbeat_service, period, liveness.clone())?;
        Ok(Self { wiring, node, liveness, heartbeat })
    }

    fn input<H: MessageHeader>(&self) -> Result<EdgeSubscriber<H>, RuntimeError> {
        let edge = &self.wiring.inputs[0];
        Ok(EdgeSubscriber::create(&self.node, &edge.service, &edge.options())?)
    }

    /// The output edge, once its readers are connected (or the stage was
    /// told to stop).
    fn output<H: MessageHeader>(&self) -> Result<Publisher<H>, RuntimeError> {
        self.output_serving(&mut || {})
    }

    /// As [`Self::output`], calling `meanwhile` while it waits for the readers.
    fn output_serving<H: MessageHeader>(&self, meanwhile: &mut dyn FnMut()) -> Result<Publisher<H>, RuntimeError> {
        let edge = &self.wiring.outputs[0];
        let publisher = Publisher::create(&self.node, &edge.service, &edge.options())?;
        let connected = publisher.wait_for_all_receivers_serving(edge.readers, READERS_WARN_EVERY, meanwhile)?;
        if connected < edge.readers {
            tracing::warn!(edge = %edge.edge, connected, expected = edge.readers, "stopped before every reader connected");
        }
        Ok(publisher)
    }

    /// Sleeps until the input wakes it; hands every valid message to
    /// `on_input`, then calls `on_drained` once the queue is empty.
    fn event_loop<H: MessageHeader>(
        &self,
        input: &EdgeSubscriber<H>,
        on_input: impl FnMut(Input<'_, H>),
        on_drained: impl FnMut(),
    ) -> Result<LoopEnd, RuntimeError> {
        self.event_loop_also(input, on_input, on_drained, None::<Attachment<'_, EdgeSubscriber<H>>>)
    }

    /// As [`Self::event_loop`], also waking on `also`.
    fn event_loop_also<H: MessageHeader, X: SynchronousMultiplexing + std::fmt::Debug>(
        &self,
        input: &EdgeSubscriber<H>,
        mut on_input: impl FnMut(Input<'_, H>),
        mut on_drained: impl FnMut(),
        mut also: Option<Attachment<'_, X>>,
    ) -> Result<LoopEnd, RuntimeError> {
        let waitset = WaitSetBuilder::new().create::<Ipc>().map_err(waitset_error)?;
        let input_guard = waitset.attach_notification(input).map_err(waitset_error)?;
        let also_guard = match &also {
            Some(a) => Some(waitset.attach_notification(a.source).map_err(waitset_error)?),
            None => None,
        };
        // A wake-up that never comes would leave a full queue unread and its
        // writer blocked on it forever: look at the queue now and then.
        let safety_tick = waitset.attach_interval(LOST_WAKEUP_CHECK).map_err(waitset_error)?;
        let mut ended = false;
        let mut failure = None;
        let mut input_events = false;
        // Runs the handler on whatever is queued, then the drained hook.
        let drain_queued = |on_input: &mut _, on_drained: &mut dyn FnMut()| {
            drain(input, &self.liveness, on_input).map(|handled| {
                if handled {
                    on_drained()
                }
            })
        };
        // Messages queued before the loop started woke no one.
        drain_queued(&mut on_input, &mut on_drained)?;
        let run = waitset.wait_and_process(|id| {
            if id.has_event_from(&safety_tick) {
                let woken = std::mem::take(&mut input_events);
                let step = input.has_messages().and_then(|queued| {
                    if queued && !woken {
                        tracing::warn!(
                            edge = input.name(),
                            "messages waited a whole check without a wake-up; reading them"
                        );
                    }
                    if queued { drain_queued(&mut on_input, &mut on_drained) } else { Ok(()) }
                });
                if let Err(err) = step {
                    failure = Some(err.into());
                    return CallbackProgression::Stop;
                }
                return CallbackProgression::Continue;
            }
            if let (Some(guard), Some(a)) = (&also_guard, &mut also)
                && id.has_event_from(guard)
                && let Err(err) = (a.on_event)()
            {
                failure = Some(err.into());
                return CallbackProgression::Stop;
            }
            if id.has_event_from(&input_guard) {
                input_events = true;
                let step = input.take_events().and_then(|end| {
                    ended |= end;
                    drain(input, &self.liveness, &mut on_input)
                });
                if let Ok(true) = step {
                    on_drained();
                }
                if let Err(err) = step {
                    failure = Some(err.into());
                    return CallbackProgression::Stop;
                }
                if ended {
                    return CallbackProgression::Stop;
                }
            }
            CallbackProgression::Continue
        });
        if let Some(err) = failure {
            return Err(err);
        }
        match run.map_err(waitset_error)? {
            WaitSetRunResult::StopRequest if ended => Ok(LoopEnd::EndOfStream),
            _ => Ok(LoopEnd::Terminated),
        }
    }

    fn finish(self) {
        self.liveness.set_state(StageState::Finished);
        self.heartbeat.finish();
    }
}

/// Takes every queued message, rejects those that break their contract,
/// counts gaps, times the handler. Returns whether any was handled.
fn drain<H: MessageHeader>(
    input: &EdgeSubscriber<H>,
    liveness: &Liveness,
    on_input: &mut impl FnMut(Input<'_, H>),
) -> Result<bool, TransportError> {
    let mut handled = false;
    while let Some(message) = input.receive()? {
        let header = message.header();
        let frame = header.header().frame_id;
        if let Err(err) = header.check_payload(message.payload()) {
            liveness.count_error();
            tracing::warn!(edge = input.name(), frame, err = %error_chain(&err), "message rejected");
            continue;
        }
        liveness.count_received(frame);
        if header.header().has_flag(flags::UPSTREAM_RESTARTED) {
            tracing::warn!(edge = input.name(), frame, "a stage upstream restarted before this frame");
        }
        let _span = tracing::debug_span!("frame", id = frame).entered();
        let started = Instant::now();
        liveness.work_started();
        on_input(Input { header, payload: message.payload() });
        liveness.work_finished(started.elapsed());
        handled = true;
    }
    Ok(handled)
}

/// Writes outputs straight into loaned shared memory.
struct IpcEmitter<'a, H: MessageHeader> {
    publisher: &'a Publisher<H>,
    slot: Option<StampSlot>,
    liveness: &'a Liveness,
    /// Called while a full queue holds a send back.
    while_blocked: &'a mut dyn FnMut(),
}

impl<H: MessageHeader> Emitter<H> for IpcEmitter<'_, H> {
    fn emit(&mut self, mut header: H, len: usize, fill: &mut dyn FnMut(&mut [f32])) -> Result<(), EmitError> {
        if let Some(slot) = self.slot {
            header.header_mut().stamps.stamp(slot);
        }
        let announced = self.liveness.announce_restart(header.header_mut());
        self.liveness.send_started();
        let sent = self.publisher.publish_serving(header, len, fill, self.while_blocked);
        self.liveness.send_finished();
        if sent.is_err() && announced {
            self.liveness.restarted();
        }
        let receivers = sent?;
        tracing::trace!(receivers, "published");
        count_undelivered(self.publisher, receivers, self.liveness);
        self.liveness.count_sent();
        Ok(())
    }
}

/// A sample that missed a reader is lost to it: counted as a drop, not
/// silent.
fn count_undelivered<H: MessageHeader>(output: &Publisher<H>, receivers: usize, liveness: &Liveness) {
    if output.missed_a_reader(receivers) {
        liveness.count_dropped(1);
    }
}

fn finish_output<H: MessageHeader>(output: &Publisher<H>, meanwhile: impl FnMut() -> Result<(), TransportError>) {
    match output.end_of_stream_serving(END_OF_STREAM_TIMEOUT, meanwhile) {
        Ok(end) => tracing::info!(
            edge = output.name(),
            receivers = end.receivers,
            acknowledged = end.acknowledged,
            "end of stream"
        ),
        Err(err) => tracing::warn!(edge = output.name(), err = %error_chain(&err), "end of stream not delivered"),
    }
}

fn exit(result: Result<(), RuntimeError>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => fail(err),
    }
}

/// Logs why the stage process failed, with the whole cause chain.
pub(crate) fn fail(err: RuntimeError) -> ExitCode {
    init_logging();
    tracing::error!(err = %error_chain(&err), "stage failed");
    ExitCode::FAILURE
}

fn build<T, E: Into<BuildError>>(
    wiring: &StageWiring,
    make: impl FnOnce(&StageWiring) -> Result<T, E>,
) -> Result<T, RuntimeError> {
    make(wiring).map_err(|source| RuntimeError::Build { stage: wiring.stage.clone(), source: source.into() })
}

/// Runs a [`Transform`] as a graph process; `make` builds it from the
/// stage's wiring (its `params` in particular). Call it from `main`.
pub fn run_transform<T: Transform, E: Into<BuildError>>(make: impl FnOnce(&StageWiring) -> Result<T, E>) -> ExitCode {
    exit((|| {
        let process = StageProcess::start(1, 1)?;
        let mut stage = build(&process.wiring, make)?;
        let _span = tracing::info_span!("stage", name = %process.wiring.stage).entered();
        let input = process.input::<T::In>()?;
        let output = process.output::<T::Out>()?;
        tracing::info!(input = input.name(), output = output.name(), "running");
        let liveness = &process.liveness;
        let slot = process.wiring.stamp_slot(T::SLOT);
        let stage = std::cell::RefCell::new(&mut stage);
        let end = process.event_loop(
            &input,
            |message| {
                let mut emitter = IpcEmitter { publisher: &output, slot, liveness, while_blocked: &mut || {} };
                transform_one(&mut **stage.borrow_mut(), message, &mut emitter, liveness)
            },
            || {
                let mut emitter = IpcEmitter { publisher: &output, slot, liveness, while_blocked: &mut || {} };
                liveness.flush(&mut **stage.borrow_mut(), &mut emitter, Flush::Idle)
            },
        )?;
        let mut emitter = IpcEmitter { publisher: &output, slot, liveness, while_blocked: &mut || {} };
        liveness.flush(&mut **stage.borrow_mut(), &mut emitter, Flush::End);
        finish_transform(process, &input, &output, end, || Ok(()))
    })())
}

/// Hands one input to a [`Transform`], counting its failures and rejects.
fn transform_one<T: Transform>(
    stage: &mut T,
    message: Input<'_, T::In>,
    emitter: &mut dyn Emitter<T::Out>,
    liveness: &Liveness,
) {
    if let Err(err) = stage.process(message, emitter) {
        liveness.count_error();
        tracing::warn!(err = %error_chain(&err), "process failed; frame skipped");
    }
    liveness.count_errors(stage.take_rejected());
}

/// Passes end-of-stream on (when the stream ended rather than the stage
/// being stopped) and reports the stage finished.
fn finish_transform<I: MessageHeader, O: MessageHeader>(
    process: StageProcess,
    input: &EdgeSubscriber<I>,
    output: &Publisher<O>,
    end: LoopEnd,
    meanwhile: impl FnMut() -> Result<(), TransportError>,
) -> Result<(), RuntimeError> {
    if let LoopEnd::EndOfStream = end {
        process.liveness.set_state(StageState::Draining);
        finish_output(output, meanwhile);
        input.acknowledge_end()?;
    }
    process.finish();
    Ok(())
}

/// A [`Server`]'s outputs, copied out of the stage so they can be published
/// once it has returned (they are small: handles to what requests fetch).
struct HeldOutputs<H> {
    outputs: Vec<(H, Vec<f32>)>,
    slot: Option<StampSlot>,
}

impl<H: MessageHeader> Emitter<H> for HeldOutputs<H> {
    fn emit(&mut self, mut header: H, len: usize, fill: &mut dyn FnMut(&mut [f32])) -> Result<(), EmitError> {
        if let Some(slot) = self.slot {
            header.header_mut().stamps.stamp(slot);
        }
        let mut payload = vec![0.0; len];
        fill(&mut payload);
        self.outputs.push((header, payload));
        Ok(())
    }
}

impl<H: MessageHeader> HeldOutputs<H> {
    /// Publishes the held outputs in order, calling `meanwhile` while a
    /// full queue holds a send back.
    fn publish(&mut self, output: &Publisher<H>, liveness: &Liveness, meanwhile: &mut dyn FnMut()) {
        for (mut header, payload) in self.outputs.drain(..) {
            let announced = liveness.announce_restart(header.header_mut());
            liveness.send_started();
            let sent = output.publish_serving(header, payload.len(), |out| out.copy_from_slice(&payload), meanwhile);
            liveness.send_finished();
            match sent {
                Ok(receivers) => {
                    count_undelivered(output, receivers, liveness);
                    liveness.count_sent();
                }
                Err(err) => {
                    if announced {
                        liveness.restarted();
                    }
                    liveness.count_error();
                    tracing::warn!(err = %error_chain(&err), "output not sent; frame skipped");
                }
            }
        }
    }
}

/// Sends a [`Server`]'s reply into the response's loaned shared memory.
struct ReplyEmitter<'a, 'r, Req: MessageHeader, Resp: MessageHeader> {
    responder: &'a mut Responder<'r, Req, Resp>,
    slot: Option<StampSlot>,
}

impl<Req: MessageHeader, Resp: MessageHeader> Emitter<Resp> for ReplyEmitter<'_, '_, Req, Resp> {
    fn emit(&mut self, mut header: Resp, len: usize, fill: &mut dyn FnMut(&mut [f32])) -> Result<(), EmitError> {
        if let Some(slot) = self.slot {
            header.header_mut().stamps.stamp(slot);
        }
        Ok(self.responder.send(header, len, fill)?)
    }
}

/// Runs a [`Server`] as a graph process: its input and output edge as for
/// [`run_transform`], plus the one request-response edge it `serves`.
pub fn run_server<S: Server, E: Into<BuildError>>(make: impl FnOnce(&StageWiring) -> Result<S, E>) -> ExitCode {
    exit((|| {
        let process = StageProcess::start(1, 1)?;
        let wiring = &process.wiring;
        let [served] = wiring.serves.as_slice() else {
            return Err(RuntimeError::Shape {
                stage: wiring.stage.clone(),
                expected: "one request-response edge it serves",
                found: format!("{} served edge(s)", wiring.serves.len()),
            });
        };
        let mut stage = build(wiring, make)?;
        let slot = wiring.stamp_slot(S::SLOT);
        let _span = tracing::info_span!("stage", name = %wiring.stage).entered();
        let input = process.input::<S::In>()?;
        let server =
            RequestServer::<S::Request, S::Response>::create(&process.node, &served.service, served.max_payload_len)?;
        // Shared with the request handler, which outlives the event loop: it
        // keeps answering while the output drains.
        let liveness = process.liveness.clone();
        let liveness = &*liveness;
        // The stage is used by both handlers, never at the same time: the
        // WaitSet calls one callback at a time.
        let stage = std::cell::RefCell::new(&mut stage);
        let on_requests = || -> Result<(), TransportError> {
            server.serve(|header, payload, responder| {
                let frame = header.header().frame_id;
                let _span = tracing::debug_span!("request", frame).entered();
                let started = Instant::now();
                liveness.work_started();
                let request = match header.check_payload(payload) {
                    Ok(()) => Some(Input { header, payload }),
                    Err(err) => {
                        liveness.count_error();
                        tracing::warn!(err = %error_chain(&err), "request breaks its contract; answered as invalid");
                        None
                    }
                };
                let mut reply = ReplyEmitter { responder, slot };
                let mut stage = stage.borrow_mut();
                let answered = match request {
                    Some(request) => stage.answer(request, &mut reply).map_err(|e| error_chain(&e)),
                    None => stage.answer_invalid(header, &mut reply).map_err(|e| error_chain(&e)),
                };
                liveness.work_finished(started.elapsed());
                liveness.count_errors(stage.take_rejected());
                if let Err(err) = answered {
                    liveness.count_error();
                    tracing::warn!(%err, "request not answered");
                }
                Ok(())
            })?;
            Ok(())
        };
        // A restarted server's caller may be the reader it waits for (the
        // sampler asks for velocities and reads conditions): answering
        // meanwhile turns the caller's wait for a response into a quick
        // "unknown condition" instead of a timeout per request.
        let output = process.output_serving::<S::Out>(&mut || {
            if let Err(err) = on_requests() {
                tracing::warn!(err = %error_chain(&err), "requests not served while waiting for the output's readers");
            }
        })?;
        tracing::info!(input = input.name(), output = output.name(), serves = %served.edge, "running");
        let mut on_request_event = || on_requests();
        let requests = Attachment { source: &server, on_event: &mut on_request_event };
        // Outputs are held until the stage has returned, then published while
        // requests keep being answered: the reader of a full output queue may
        // be waiting for an answer before it reads again.
        let held = std::cell::RefCell::new(HeldOutputs { outputs: Vec::new(), slot });
        let publish_held = || {
            held.borrow_mut().publish(&output, liveness, &mut || {
                if let Err(err) = on_requests() {
                    tracing::warn!(err = %error_chain(&err), "requests not served while the output was full");
                }
            })
        };
        let end = process.event_loop_also(
            &input,
            |message| {
                transform_one(&mut **stage.borrow_mut(), message, &mut *held.borrow_mut(), liveness);
                publish_held();
            },
            || {
                liveness.flush(&mut **stage.borrow_mut(), &mut *held.borrow_mut(), Flush::Idle);
                publish_held();
            },
            Some(requests),
        )?;
        liveness.flush(&mut **stage.borrow_mut(), &mut *held.borrow_mut(), Flush::End);
        publish_held();
        // The readers of the handles may still be asking for velocities.
        finish_transform(process, &input, &output, end, on_requests)
    })())
}

/// Runs a [`Joined`] transform as a graph process: its input and output edge
/// as for [`run_transform`], plus the one edge in its `side_inputs`.
pub fn run_joined<J: Joined, E: Into<BuildError>>(make: impl FnOnce(&StageWiring) -> Result<J, E>) -> ExitCode {
    exit((|| {
        let process = StageProcess::start(1, 1)?;
        let wiring = &process.wiring;
        let [side_edge] = wiring.side_inputs.as_slice() else {
            return Err(RuntimeError::Shape {
                stage: wiring.stage.clone(),
                expected: "one side input",
                found: format!("{} side input(s)", wiring.side_inputs.len()),
            });
        };
        // Subscribed before the stage is built (a selector precomputes its
        // distance grids), so nothing published meanwhile is missed: the
        // edges queue and push back.
        let input = process.input::<J::In>()?;
        let side = EdgeSubscriber::<J::Side>::create(&process.node, &side_edge.service, &side_edge.options())?;
        let mut stage = build(wiring, make)?;
        let slot = wiring.stamp_slot(J::SLOT);
        let _span = tracing::info_span!("stage", name = %wiring.stage).entered();
        // In a loop the side input's writer may be this output's reader,
        // waiting on its own output's readers (this stage): answer its
        // handshake meanwhile, remembering an end of stream seen on the way.
        let side_ended_early = std::cell::Cell::new(false);
        let output = process.output_serving::<J::Out>(&mut || answer_handshake(&side, &side_ended_early))?;
        tracing::info!(input = input.name(), side = side.name(), output = output.name(), "running");
        let liveness = process.liveness.clone();
        let liveness = &*liveness;
        // Both handlers use the stage, one at a time (the WaitSet calls one
        // callback at a time).
        let stage = std::cell::RefCell::new(&mut stage);
        let mut side_ended = false;
        // Also called while the output drains at the end: a side input that
        // closes a loop ends only after this stage's output has.
        let mut on_side = || -> Result<(), TransportError> {
            let ended = side.take_events()? | side_ended_early.replace(false);
            drain_side(&side, &mut **stage.borrow_mut(), liveness)?;
            if ended && !side_ended {
                side_ended = true;
                side.acknowledge_end()?;
            }
            Ok(())
        };
        let attachment = Attachment { source: &side, on_event: &mut on_side };
        // Outputs are held until the stage has returned, then published while
        // side messages keep being read (and handed to the stage): in a loop
        // the side input's writer may be this output's reader, itself
        // waiting for room on the side input (tracking: the selector's
        // Estimates feed the sampler whose Hypotheses it reads). The writer
        // may also be restarted and waiting for this stage's READY: its
        // handshake is answered on the way.
        let held = std::cell::RefCell::new(HeldOutputs { outputs: Vec::new(), slot });
        let read_side_into = |stage: &mut J| {
            answer_handshake(&side, &side_ended_early);
            if let Err(err) = drain_side(&side, stage, liveness) {
                tracing::warn!(err = %error_chain(&err), "side input not read");
            }
        };
        let read_side = || read_side_into(&mut stage.borrow_mut());
        let publish_held = || held.borrow_mut().publish(&output, liveness, &mut || read_side());
        // Side messages published while the stage was being built woke no
        // one: a writer blocked on this full side queue would wait forever.
        read_side();
        let await_side = |next: &J::In| {
            let gave_up = crate::stage::await_side(&mut **stage.borrow_mut(), next, read_side_into);
            if gave_up {
                tracing::debug!(side = side.name(), "the awaited side message did not come in time: going on without");
            }
        };
        let end = process.event_loop_also(
            &input,
            |message| {
                await_side(message.header);
                transform_one(&mut **stage.borrow_mut(), message, &mut *held.borrow_mut(), liveness);
                publish_held();
            },
            || {
                // A batch starts from the side messages published before it runs.
                read_side();
                liveness.flush(&mut **stage.borrow_mut(), &mut *held.borrow_mut(), Flush::Idle);
                publish_held();
            },
            Some(attachment),
        )?;
        liveness.flush(&mut **stage.borrow_mut(), &mut *held.borrow_mut(), Flush::End);
        publish_held();
        // A side input that has already ended (one that closes no loop) is
        // acknowledged even when the output has no reader to wait for.
        if let Err(err) = on_side() {
            tracing::warn!(err = %error_chain(&err), "side input not read");
        }
        finish_transform(process, &input, &output, end, on_side)
    })())
}

/// Runs a stage whose side input is optional: as [`run_joined`] when its
/// graph entry lists one in `side_inputs`, else as [`run_transform`] (a
/// selector that scores without the observed points needs none).
pub fn run_transform_or_joined<T: Transform + Joined, E: Into<BuildError>>(
    make: impl FnOnce(&StageWiring) -> Result<T, E>,
) -> ExitCode {
    let has_side_input = StageWiring::from_env().is_ok_and(|w| !w.side_inputs.is_empty());
    if has_side_input { run_joined(make) } else { run_transform(make) }
}

/// Answers a new writer's handshake on `side` without reading its messages,
/// remembering an end of stream seen on the way in `ended`.
fn answer_handshake<H: MessageHeader>(side: &EdgeSubscriber<H>, ended: &std::cell::Cell<bool>) {
    match side.take_events() {
        Ok(end) => ended.set(ended.get() | end),
        Err(err) => tracing::warn!(err = %error_chain(&err), "side input's handshake not answered"),
    }
}

/// Hands every queued side message to the stage. Side messages are not
/// frames of this stage's stream: they are checked against their contract
/// but not counted as inputs or gaps.
fn drain_side<J: Joined>(
    side: &EdgeSubscriber<J::Side>,
    stage: &mut J,
    liveness: &Liveness,
) -> Result<(), TransportError> {
    while let Some(message) = side.receive()? {
        let header = message.header();
        let frame = header.header().frame_id;
        let kept = header
            .check_payload(message.payload())
            .map_err(|e| error_chain(&e))
            .and_then(|()| stage.side(Input { header, payload: message.payload() }).map_err(|e| error_chain(&e)));
        if let Err(err) = kept {
            liveness.count_error();
            tracing::warn!(edge = side.name(), frame, %err, "side message rejected");
        }
    }
    Ok(())
}

/// Runs a [`Sink`] as a graph process.
pub fn run_sink<K: Sink, E: Into<BuildError>>(make: impl FnOnce(&StageWiring) -> Result<K, E>) -> ExitCode {
    exit((|| {
        let process = StageProcess::start(1, 0)?;
        let mut sink = build(&process.wiring, make)?;
        let _span = tracing::info_span!("stage", name = %process.wiring.stage).entered();
        let input = process.input::<K::In>()?;
        tracing::info!(input = input.name(), "running");
        let liveness = &process.liveness;
        let end = process.event_loop(
            &input,
            |message| {
                if let Err(err) = sink.consume(message) {
                    liveness.count_error();
                    tracing::warn!(err = %error_chain(&err), "consume failed; frame skipped");
                }
            },
            || {},
        )?;
        if let Err(err) = sink.finish() {
            tracing::error!(err = %error_chain(&err), "sink could not finish");
        }
        if let LoopEnd::EndOfStream = end {
            input.acknowledge_end()?;
        }
        process.finish();
        Ok(())
    })())
}

/// Runs a [`Source`] as a graph process. With a `rate_hz` parameter it emits
/// on a timer; without, as fast as its output edge accepts.
pub fn run_source<S: Source, E: Into<BuildError>>(make: impl FnOnce(&StageWiring) -> Result<S, E>) -> ExitCode {
    exit((|| {
        let process = StageProcess::start(0, 1)?;
        let mut source = build(&process.wiring, make)?;
        let _span = tracing::info_span!("stage", name = %process.wiring.stage).entered();
        let output = process.output::<S::Out>()?;
        let rate_hz = process.wiring.params.get("rate_hz").and_then(|v| v.as_f64()).filter(|hz| *hz > 0.0);
        tracing::info!(output = output.name(), ?rate_hz, "running");
        let liveness = &process.liveness;
        let slot = process.wiring.stamp_slot(S::SLOT);
        let mut step = || -> SourceStep {
            let mut emitter = IpcEmitter { publisher: &output, slot, liveness, while_blocked: &mut || {} };
            let started = Instant::now();
            liveness.work_started();
            let result = source.next(&mut emitter);
            liveness.source_step_finished(result.as_ref().ok().copied(), started.elapsed());
            liveness.count_errors(source.take_rejected());
            result.unwrap_or_else(|err| {
                liveness.count_error();
                tracing::warn!(err = %error_chain(&err), "source failed; frame skipped");
                SourceStep::Continue
            })
        };
        let finished = match rate_hz {
            Some(hz) => paced(Duration::from_secs_f64(1.0 / hz), &mut step)?,
            // As fast as possible; `wait(0)` only checks for SIGINT/SIGTERM.
            None => loop {
                if process.node.wait(Duration::ZERO).is_err() {
                    break false;
                }
                if step() == SourceStep::Finished {
                    break true;
                }
            },
        };
        if finished {
            process.liveness.set_state(StageState::Draining);
            finish_output(&output, || Ok(()));
        }
        process.finish();
        Ok(())
    })())
}

/// The timer-driven source loop; returns whether the source finished.
fn paced(period: Duration, step: &mut impl FnMut() -> SourceStep) -> Result<bool, RuntimeError> {
    let waitset = WaitSetBuilder::new().create::<Ipc>().map_err(waitset_error)?;
    let tick = waitset.attach_interval(period).map_err(waitset_error)?;
    let mut finished = false;
    waitset
        .wait_and_process(|id| {
            if id.has_event_from(&tick) && step() == SourceStep::Finished {
                finished = true;
                return CallbackProgression::Stop;
            }
            CallbackProgression::Continue
        })
        .map_err(waitset_error)?;
    Ok(finished)
}
