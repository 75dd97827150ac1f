use std::sync::{Arc, Mutex};

use poseflow_contracts::{Header, HypothesesHeader, POSE_LEN, VELOCITY_LEN, VelocityRequest, VelocityResponse, status};
use poseflow_graph::{EdgeWiring, OverflowPolicy};

use super::*;
use crate::call::{Call, connect};
use crate::local::DriveError;

#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct TestError(String);

impl From<EmitError> for TestError {
    fn from(err: EmitError) -> Self {
        TestError(err.to_string())
    }
}

fn hypotheses(frame: u64) -> HypothesesHeader {
    HypothesesHeader { header: Header::new(frame, 1), sample_count: 1, step_count: 1, ..Default::default() }
}

/// Frames 0..n, one pose each, every value the frame number.
struct Counter(u64, u64);

impl Source for Counter {
    type Out = HypothesesHeader;
    type Error = TestError;
    const SLOT: Option<StampSlot> = None;

    fn next(&mut self, output: &mut dyn Emitter<HypothesesHeader>) -> Result<SourceStep, TestError> {
        if self.0 == self.1 {
            return Ok(SourceStep::Finished);
        }
        let frame = self.0;
        self.0 += 1;
        output.emit(hypotheses(frame), POSE_LEN, &mut |out| out.fill(frame as f32))?;
        Ok(SourceStep::Continue)
    }
}

/// Passes its input on and answers each velocity request with twice the
/// request's first value.
struct Doubler;

/// Emits the input unchanged: the body of every pass-through test stage.
fn pass_on(input: Input<'_, HypothesesHeader>, output: &mut dyn Emitter<HypothesesHeader>) -> Result<(), TestError> {
    Ok(output.emit(*input.header, input.payload.len(), &mut |out| out.copy_from_slice(input.payload))?)
}

impl Transform for Doubler {
    type In = HypothesesHeader;
    type Out = HypothesesHeader;
    type Error = TestError;
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        output: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), TestError> {
        pass_on(input, output)
    }
}

impl Server for Doubler {
    type Request = VelocityRequest;
    type Response = VelocityResponse;

    fn answer(
        &mut self,
        request: Input<'_, VelocityRequest>,
        reply: &mut dyn Emitter<VelocityResponse>,
    ) -> Result<(), TestError> {
        let header = VelocityResponse {
            header: request.header.header,
            request_id: request.header.request_id,
            sample_count: 1,
            status: status::OK,
        };
        let doubled = 2.0 * request.payload[0];
        Ok(reply.emit(header, VELOCITY_LEN, &mut |out| out.fill(doubled))?)
    }

    fn answer_invalid(
        &mut self,
        _request: &VelocityRequest,
        _reply: &mut dyn Emitter<VelocityResponse>,
    ) -> Result<(), TestError> {
        Err(TestError("invalid request".into()))
    }
}

/// Asks the server about each input; outputs the answer. Also a joined
/// stage: it notes whether each input's frame came by the side input
/// first.
struct Asker {
    client: Box<dyn Call<VelocityRequest, VelocityResponse>>,
    seen_on_side: Vec<u64>,
    side_first: Arc<Mutex<Vec<bool>>>,
}

impl Transform for Asker {
    type In = HypothesesHeader;
    type Out = HypothesesHeader;
    type Error = TestError;
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        output: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), TestError> {
        let frame = input.header.header.frame_id;
        self.side_first.lock().unwrap().push(self.seen_on_side.contains(&frame));
        let request = VelocityRequest::single(input.header.header, 0, frame, 1, 0.5);
        let mut answer = None;
        self.client
            .call(request, input.payload, Duration::from_secs(5), &mut |_, payload| answer = Some(payload[0]))
            .map_err(|e| TestError(e.to_string()))?;
        let answer = answer.ok_or_else(|| TestError("no answer".into()))?;
        Ok(output.emit(*input.header, POSE_LEN, &mut |out| out.fill(answer))?)
    }
}

impl Joined for Asker {
    type Side = HypothesesHeader;

    fn side(&mut self, input: Input<'_, HypothesesHeader>) -> Result<(), TestError> {
        self.seen_on_side.push(input.header.header.frame_id);
        Ok(())
    }
}

struct Collect(Arc<Mutex<Vec<f32>>>);

impl Sink for Collect {
    type In = HypothesesHeader;
    type Error = TestError;

    fn consume(&mut self, input: Input<'_, HypothesesHeader>) -> Result<(), TestError> {
        self.0.lock().unwrap().push(input.payload[0]);
        Ok(())
    }

    fn finish(&mut self) -> Result<(), TestError> {
        Ok(())
    }
}

fn velocities_edge(service: &str) -> EdgeWiring {
    EdgeWiring {
        edge: "velocities".into(),
        service: service.into(),
        message: "Velocity".into(),
        queue: 1,
        overflow: OverflowPolicy::Block,
        max_payload_len: 64,
        readers: 1,
    }
}

/// counter → doubler (serving velocities) → asker (calling it; the
/// counter's output as its side input) → collect, with one-slot
/// blocking queues: every frame arrives doubled and in order, each
/// input's side message was handed over before it, and the server
/// answers while its own output is full.
#[test]
fn a_server_answers_its_in_process_caller_and_side_inputs_come_first() {
    const FRAMES: u64 = 200;
    let service = "poseflow/local-test/velocities";
    let mut local = LocalGraph::new();
    for edge in ["raw", "passed", "asked"] {
        local.edge(edge, 1, LocalOverflow::Block);
    }
    let collected = Arc::new(Mutex::new(Vec::new()));
    let side_first = Arc::new(Mutex::new(Vec::new()));
    local.add_source("counter", || Ok(Counter(0, FRAMES)), "raw", None).unwrap();
    local.add_server("doubler", || Ok(Doubler), "raw", service, "passed").unwrap();
    let side = side_first.clone();
    let make_asker = move || -> Result<Asker, BuildError> {
        let client = connect("asker", &velocities_edge(service))?;
        Ok(Asker { client, seen_on_side: Vec::new(), side_first: side })
    };
    local.add_joined("asker", make_asker, "passed", "raw", "asked").unwrap();
    let sink = collected.clone();
    local.add_sink("collect", move || Ok(Collect(sink)), "asked").unwrap();

    let report = local.run(Arc::new(AtomicBool::new(false))).unwrap();
    let expected: Vec<f32> = (0..FRAMES).map(|f| 2.0 * f as f32).collect();
    assert_eq!(*collected.lock().unwrap(), expected);
    assert!(side_first.lock().unwrap().iter().all(|&first| first));
    assert_eq!(report["asker"].errors, 0);
    assert_eq!(report["doubler"].frames_out, FRAMES);
}

#[test]
fn a_stage_that_cannot_be_built_stops_the_graph_and_is_named() {
    let mut local = LocalGraph::new();
    local.edge("raw", 1, LocalOverflow::Block);
    local.add_source("counter", || Ok(Counter(0, u64::MAX)), "raw", None).unwrap();
    local.add_sink("broken", || Err::<Collect, _>("no such model".into()), "raw").unwrap();
    let err = local.run(Arc::new(AtomicBool::new(false))).unwrap_err();
    assert_eq!(crate::error_chain(&err), "stage `broken`: cannot build from its parameters: no such model");
}

/// The same server and joined stage driven from outside, one frame at a
/// time: after each settle, the collector holds exactly that frame's
/// answer (nothing is still on its way), and dropping the feed ends the
/// graph.
#[test]
fn a_driven_graph_settles_after_each_message_with_its_result_collected() {
    const FRAMES: u64 = 50;
    let service = "poseflow/local-test/driven-velocities";
    let mut local = LocalGraph::new();
    for edge in ["raw", "passed", "asked"] {
        local.edge(edge, 1, LocalOverflow::Block);
    }
    let feed = local.feed::<HypothesesHeader>("raw").unwrap();
    let collected = local.collect::<HypothesesHeader>("asked").unwrap();
    local.add_server("doubler", || Ok(Doubler), "raw", service, "passed").unwrap();
    let side_first = Arc::new(Mutex::new(Vec::new()));
    let side = side_first.clone();
    let make_asker = move || -> Result<Asker, BuildError> {
        let client = connect("asker", &velocities_edge(service))?;
        Ok(Asker { client, seen_on_side: Vec::new(), side_first: side })
    };
    local.add_joined("asker", make_asker, "passed", "raw", "asked").unwrap();
    assert!(matches!(feed.send(hypotheses(0), vec![0.0; POSE_LEN]), Err(DriveError::NotStarted { .. })));

    let mut running = local.start(Arc::new(AtomicBool::new(false)));
    for frame in 0..FRAMES {
        feed.send(hypotheses(frame), vec![frame as f32; POSE_LEN]).unwrap();
        running.settle(Duration::from_secs(10)).unwrap();
        let out = collected.drain();
        assert_eq!(out.len(), 1, "frame {frame}");
        assert_eq!(out[0].0.header.frame_id, frame);
        assert_eq!(out[0].1[0], 2.0 * frame as f32);
    }
    let err = feed.send(hypotheses(0), vec![0.0; 3]).unwrap_err();
    assert!(matches!(err, DriveError::Message { .. }), "{err}");
    drop(feed);
    let report = running.finish().unwrap();
    assert_eq!(report["doubler"].frames_out, FRAMES);
    assert!(side_first.lock().unwrap().iter().all(|&first| first));
}

#[test]
fn settling_a_graph_whose_stage_cannot_be_built_names_the_stage() {
    let mut local = LocalGraph::new();
    local.edge("raw", 1, LocalOverflow::Block);
    let feed = local.feed::<HypothesesHeader>("raw").unwrap();
    local.add_sink("broken", || Err::<Collect, _>("no such model".into()), "raw").unwrap();
    let mut running = local.start(Arc::new(AtomicBool::new(false)));
    let _ = feed.send(hypotheses(0), vec![0.0; POSE_LEN]);
    let err = running.settle(Duration::from_secs(10)).unwrap_err();
    assert_eq!(crate::error_chain(&err), "stage `broken`: cannot build from its parameters: no such model");
}

/// Holds its inputs and passes them on in `flush`, each output's payload
/// the size of the batch it went in.
#[derive(Default)]
struct Batcher(Vec<HypothesesHeader>);

impl Transform for Batcher {
    type In = HypothesesHeader;
    type Out = HypothesesHeader;
    type Error = TestError;
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        _: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), TestError> {
        self.0.push(*input.header);
        Ok(())
    }

    fn flush(&mut self, output: &mut dyn Emitter<HypothesesHeader>, _: Flush) -> Result<(), TestError> {
        // Slow, as a network run is: what is fed meanwhile queues up.
        std::thread::sleep(Duration::from_millis(20));
        let size = self.0.len() as f32;
        for header in self.0.drain(..) {
            output.emit(header, POSE_LEN, &mut |out| out.fill(size))?;
        }
        Ok(())
    }
}

impl Joined for Batcher {
    type Side = HypothesesHeader;

    fn side(&mut self, _: Input<'_, HypothesesHeader>) -> Result<(), TestError> {
        Ok(())
    }
}

impl Server for Batcher {
    type Request = VelocityRequest;
    type Response = VelocityResponse;

    fn answer(
        &mut self,
        request: Input<'_, VelocityRequest>,
        reply: &mut dyn Emitter<VelocityResponse>,
    ) -> Result<(), TestError> {
        self.answer_invalid(request.header, reply)
    }

    fn answer_invalid(
        &mut self,
        request: &VelocityRequest,
        reply: &mut dyn Emitter<VelocityResponse>,
    ) -> Result<(), TestError> {
        let header = VelocityResponse {
            header: request.header,
            request_id: request.request_id,
            sample_count: 0,
            status: status::INVALID_REQUEST,
        };
        Ok(reply.emit(header, 0, &mut |_| {})?)
    }
}

/// A batching stage between two others, in every local shape (transform,
/// joined, server): what it holds is flushed when its queue runs empty, so
/// a driven graph settles with every frame's output collected, and the
/// frames fed at once while it is busy go in batches of more than one.
#[test]
fn a_batching_stage_is_flushed_whenever_its_queue_runs_empty() {
    for shape in ["transform", "joined", "server"] {
        let service = format!("poseflow/local-test/batching-{shape}");
        let mut local = LocalGraph::new();
        for edge in ["raw", "side", "batched"] {
            local.edge(edge, 64, LocalOverflow::Block);
        }
        let feed = local.feed::<HypothesesHeader>("raw").unwrap();
        let _side = local.feed::<HypothesesHeader>("side").unwrap();
        let collected = local.collect::<HypothesesHeader>("batched").unwrap();
        match shape {
            "transform" => local.add_transform("batcher", || Ok(Batcher::default()), "raw", "batched").unwrap(),
            "joined" => local.add_joined("batcher", || Ok(Batcher::default()), "raw", "side", "batched").unwrap(),
            _ => local.add_server("batcher", || Ok(Batcher::default()), "raw", &service, "batched").unwrap(),
        }
        let mut running = local.start(Arc::new(AtomicBool::new(false)));
        // One at a time: a batch of one each, nothing left held.
        for frame in 0..5 {
            feed.send(hypotheses(frame), vec![0.0; POSE_LEN]).unwrap();
            running.settle(Duration::from_secs(10)).unwrap();
            let out = collected.drain();
            assert_eq!((out.len(), out[0].1[0]), (1, 1.0), "{shape} frame {frame}");
        }
        // Forty at once: every one comes out, some of them together.
        for frame in 5..45 {
            feed.send(hypotheses(frame), vec![0.0; POSE_LEN]).unwrap();
        }
        running.settle(Duration::from_secs(10)).unwrap();
        let out = collected.drain();
        let frames: Vec<u64> = out.iter().map(|(h, _)| h.header.frame_id).collect();
        assert_eq!(frames, (5..45).collect::<Vec<_>>(), "{shape}");
        assert!(out.iter().any(|(_, p)| p[0] > 1.0), "{shape}: no batch of more than one");
        drop(feed);
        running.finish().unwrap();
    }
}

/// Passes each input on after a pause: the slow stage of a loop.
struct Slow(Duration);

impl Transform for Slow {
    type In = HypothesesHeader;
    type Out = HypothesesHeader;
    type Error = TestError;
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        output: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), TestError> {
        std::thread::sleep(self.0);
        pass_on(input, output)
    }
}

/// Passes its input on and notes, for each, whether the side input had
/// brought the frame before it back; with `awaits`, waits for that.
struct Follower {
    awaits: bool,
    sent: Option<u64>,
    back: Option<u64>,
    had_previous: Arc<Mutex<Vec<bool>>>,
}

impl Transform for Follower {
    type In = HypothesesHeader;
    type Out = HypothesesHeader;
    type Error = TestError;
    const SLOT: Option<StampSlot> = None;

    fn process(
        &mut self,
        input: Input<'_, HypothesesHeader>,
        output: &mut dyn Emitter<HypothesesHeader>,
    ) -> Result<(), TestError> {
        let frame = input.header.header.frame_id;
        self.had_previous.lock().unwrap().push(frame == 0 || self.back >= Some(frame - 1));
        self.sent = Some(frame);
        pass_on(input, output)
    }
}

impl Joined for Follower {
    type Side = HypothesesHeader;

    fn side(&mut self, input: Input<'_, HypothesesHeader>) -> Result<(), TestError> {
        self.back = self.back.max(Some(input.header.header.frame_id));
        Ok(())
    }

    fn awaits_side(&self, _next: &HypothesesHeader) -> Option<Duration> {
        (self.awaits && self.back < self.sent).then_some(Duration::from_secs(5))
    }
}

/// counter → follower → slow (3 ms) → back to the follower's side input,
/// as the tracking sampler and the selector: awaiting, every frame is
/// handled after the frame before it came back; not awaiting, frames
/// overtake the loop.
#[test]
fn a_joined_stage_that_awaits_its_side_input_sees_the_loop_close_first() {
    const FRAMES: u64 = 40;
    let run = |awaits: bool| {
        let mut local = LocalGraph::new();
        for edge in ["raw", "followed", "back"] {
            local.edge(edge, 2, LocalOverflow::Block);
        }
        let had_previous = Arc::new(Mutex::new(Vec::new()));
        let noted = had_previous.clone();
        local.add_source("counter", || Ok(Counter(0, FRAMES)), "raw", None).unwrap();
        let follower = move || Ok(Follower { awaits, sent: None, back: None, had_previous: noted });
        local.add_joined("follower", follower, "raw", "back", "followed").unwrap();
        local.add_transform("slow", || Ok(Slow(Duration::from_millis(3))), "followed", "back").unwrap();
        let report = local.run(Arc::new(AtomicBool::new(false))).unwrap();
        assert_eq!(report["slow"].frames_out, FRAMES);
        had_previous.lock().unwrap().clone()
    };
    let awaited = run(true);
    assert_eq!(awaited.len(), FRAMES as usize);
    assert!(awaited.iter().all(|&had| had), "{awaited:?}");
    let raced = run(false);
    assert!(raced.iter().any(|&had| !had), "without waiting, frames overtake the loop: {raced:?}");
}
