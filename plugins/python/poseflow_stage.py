"""Write a PoseFlow stage in Python.

A stage started by `poseflow run` finds its wiring (service names, queue
settings, parameters) as JSON in the environment variable POSEFLOW_STAGE.
This module speaks the same protocol as the Rust runtime
(`shared/runtime`, `shared/transport`) over iceoryx2's Python bindings:

- every edge is a publish-subscribe service `[f32]` with a contract header
  as user header, plus an event service of the same name (DATA,
  END_OF_STREAM, PUBLISHER_CONNECTED) and one named `<edge>/ack` (READY,
  END_ACKNOWLEDGED);
- a receiver announces READY once connected; a publisher waits for READY
  from its readers before its first sample;
- at the end of a stream the publisher sends END_OF_STREAM and waits until
  each receiver has drained and sent END_ACKNOWLEDGED;
- a Heartbeat is published on the stage's heartbeat service every
  `heartbeat_ms`; the last one is handed over with the same end-of-stream
  handshake.

Layouts are those of `shared/contracts` (see its crate docs); the ctypes
structures below mirror them field by field.
"""

import ctypes
import json
import os
import signal
import time

import iceoryx2 as iox2

STAGE_SLOTS = 8
# Timestamp slots (shared/contracts/src/header.rs, `StampSlot`), by their
# names in graph files (`stamp = "..."`).
SLOT_SOURCE, SLOT_INGEST, SLOT_ENCODE, SLOT_SAMPLER, SLOT_SELECTOR, SLOT_GRASP, SLOT_NEXT_VIEW, SLOT_SINK = range(8)
SLOT_NAMES = ("source", "ingest", "encode", "sampler", "selector", "grasp", "next_view", "sink")
SELECTION_METHODS = {0: "none", 1: "model-free", 2: "chamfer", 3: "sdf"}

# Event ids on `<edge>` and on `<edge>/ack` (shared/transport/src/pubsub.rs).
DATA, END_OF_STREAM, PUBLISHER_CONNECTED = 0, 1, 2
END_ACKNOWLEDGED, READY = 0, 1
EVENT_ID_MAX = 2
# Service capacities (must equal the Rust side's, iceoryx2 checks them).
MAX_PUBLISHERS, MAX_SUBSCRIBERS, MAX_NODES = 4, 16, 32

STATE_RUNNING, STATE_DRAINING, STATE_FINISHED = 1, 2, 3


class StageStamps(ctypes.Structure):
    _fields_ = [("ns", ctypes.c_uint64 * STAGE_SLOTS)]


class Header(ctypes.Structure):
    _fields_ = [
        ("frame_id", ctypes.c_uint64),
        ("object_id", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
        ("stamps", StageStamps),
    ]


class ObjectCategory(ctypes.Structure):
    """A category-level model's category code (REAL275's: 1 bottle, 2 bowl,
    3 camera, 4 can, 5 laptop, 6 mug; 0 = none) and the object's box extents
    along its canonical x, y, z in metres (shared/contracts/src/category.rs)."""

    _fields_ = [("code", ctypes.c_uint32), ("size", ctypes.c_float * 3)]


class HypothesesHeader(ctypes.Structure):
    _fields_ = [
        ("header", Header),
        ("sample_count", ctypes.c_uint32),
        ("step_count", ctypes.c_uint32),
        ("category", ObjectCategory),
    ]

    @staticmethod
    def type_name():
        return "poseflow/Hypotheses/v2"

    def payload_len(self):
        return 12 * self.sample_count


class CameraIntrinsics(ctypes.Structure):
    _fields_ = [
        ("fx", ctypes.c_float),
        ("fy", ctypes.c_float),
        ("cx", ctypes.c_float),
        ("cy", ctypes.c_float),
        ("width", ctypes.c_uint32),
        ("height", ctypes.c_uint32),
    ]


# f32 values of one detection record of a Frame:
# obj_id, instance, score, x, y, width, height, mask_offset.
DETECTION_LEN = 8


class FrameHeader(ctypes.Structure):
    """An RGB-D frame with detections (shared/contracts/src/frame.rs).

    Payload: rgb 3·W·H (RGB interleaved, 0-255) ‖ depth W·H (metres) ‖
    detections M·8 ‖ masks (each detection's box, row-major, 1 = object)."""

    _fields_ = [
        ("header", Header),
        ("intrinsics", CameraIntrinsics),
        ("scene_id", ctypes.c_uint32),
        ("image_id", ctypes.c_uint32),
        ("detection_count", ctypes.c_uint32),
        ("mask_len", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name():
        return "poseflow/Frame/v1"

    def payload_len(self):
        pixels = self.intrinsics.width * self.intrinsics.height
        return 4 * pixels + DETECTION_LEN * self.detection_count + self.mask_len


class Heartbeat(ctypes.Structure):
    _fields_ = [
        ("header", Header),
        ("pid", ctypes.c_uint32),
        ("state", ctypes.c_uint32),
        ("frames_in", ctypes.c_uint64),
        ("frames_out", ctypes.c_uint64),
        ("dropped", ctypes.c_uint64),
        ("errors", ctypes.c_uint64),
        ("latency_p50_us", ctypes.c_uint32),
        ("latency_p99_us", ctypes.c_uint32),
        ("busy_us", ctypes.c_uint32),
        ("blocked_us", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name():
        return "poseflow/Heartbeat/v1"

    def payload_len(self):
        return 0


# f32 values per record (shared/contracts): a pose is R row-major (9) ‖ t
# in metres (3), camera from object; a weighted pose adds its weight.
POSE_LEN = 12
VELOCITY_LEN = 6
WEIGHTED_POSE_LEN = POSE_LEN + 1
GRASP_LEN = POSE_LEN + 3
CANDIDATE_LEN = POSE_LEN + 1


class ObservationHeader(ctypes.Structure):
    """One object's network input (shared/contracts/src/observation.rs).

    Payload: image 3·S·S (CHW, normalised) ‖ token mask P·P ‖ points N·3
    (centred on `centroid`, divided by `point_scale`) ‖ depth G·G (metres,
    0 = none) ‖ mask G·G, G = `depth_grid` (0: no such sections), over the
    crop scaled by `depth_span` about its centre."""

    _fields_ = [
        ("header", Header),
        ("intrinsics", CameraIntrinsics),
        ("centroid", ctypes.c_float * 3),
        ("point_scale", ctypes.c_float),
        ("crop", ctypes.c_float * 4),
        ("image_size", ctypes.c_uint32),
        ("patch_grid", ctypes.c_uint32),
        ("point_count", ctypes.c_uint32),
        ("valid_point_count", ctypes.c_uint32),
        ("depth_grid", ctypes.c_uint32),
        ("depth_span", ctypes.c_float),
    ]

    @staticmethod
    def type_name():
        return "poseflow/Observation/v2"

    def payload_len(self):
        return 3 * self.image_size**2 + self.patch_grid**2 + 3 * self.point_count + 2 * self.depth_grid**2


class ConditionHandle(ctypes.Structure):
    """A condition cached by the inference stage; no payload
    (shared/contracts/src/condition.rs)."""

    _fields_ = [
        ("header", Header),
        ("condition_id", ctypes.c_uint64),
        ("image_tokens", ctypes.c_uint32),
        ("point_tokens", ctypes.c_uint32),
        ("active_image_tokens", ctypes.c_uint32),
        ("model_width", ctypes.c_uint32),
        ("centroid", ctypes.c_float * 3),
        ("point_scale", ctypes.c_float),
        ("category", ObjectCategory),
    ]

    @staticmethod
    def type_name():
        return "poseflow/Condition/v2"

    def payload_len(self):
        return 0


MAX_SEGMENTS = 16


class VelocitySegment(ctypes.Structure):
    """A run of a VelocityRequest's samples under one condition at one flow time."""

    _fields_ = [
        ("condition_id", ctypes.c_uint64),
        ("sample_count", ctypes.c_uint32),
        ("t", ctypes.c_float),
    ]


class VelocityRequest(ctypes.Structure):
    """Payload: N poses (POSE_LEN each), the segments' samples one segment
    after the other (shared/contracts/src/velocity.rs)."""

    _fields_ = [
        ("header", Header),
        ("request_id", ctypes.c_uint64),
        ("segment_count", ctypes.c_uint32),
        ("sample_count", ctypes.c_uint32),
        ("step_index", ctypes.c_uint32),
        ("step_count", ctypes.c_uint32),
        ("segments", VelocitySegment * MAX_SEGMENTS),
    ]

    @staticmethod
    def type_name():
        return "poseflow/VelocityRequest/v2"

    def payload_len(self):
        return POSE_LEN * self.sample_count


class VelocityResponse(ctypes.Structure):
    """Payload: N velocities (ω ‖ v, VELOCITY_LEN each) when status is 0 (OK), else none."""

    _fields_ = [
        ("header", Header),
        ("request_id", ctypes.c_uint64),
        ("sample_count", ctypes.c_uint32),
        ("status", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name():
        return "poseflow/VelocityResponse/v1"

    def payload_len(self):
        return VELOCITY_LEN * self.sample_count if self.status == 0 else 0


class EstimateHeader(ctypes.Structure):
    """The selected pose and the distribution around it
    (shared/contracts/src/estimate.rs). `best` and `mean` are poses
    (POSE_LEN); `covariance` is the 6×6 row-major tangent covariance at
    `mean`, order t ‖ ω (m², rad²); `selection` 0 none, 1 model-free,
    2 chamfer, 3 sdf.

    Payload: modes M·13 ‖ hypotheses N·13 (pose ‖ weight); the first
    `kept_count` hypotheses are the kept ones."""

    _fields_ = [
        ("header", Header),
        ("best", ctypes.c_float * POSE_LEN),
        ("mean", ctypes.c_float * POSE_LEN),
        ("covariance", ctypes.c_float * 36),
        ("rotation_trace", ctypes.c_float),
        ("selection", ctypes.c_uint32),
        ("mode_count", ctypes.c_uint32),
        ("hypothesis_count", ctypes.c_uint32),
        ("kept_count", ctypes.c_uint32),
        ("refined", ctypes.c_uint32),
        ("category", ObjectCategory),
    ]

    @staticmethod
    def type_name():
        return "poseflow/Estimate/v3"

    def payload_len(self):
        return WEIGHTED_POSE_LEN * (self.mode_count + self.hypothesis_count)


class GraspsHeader(ctypes.Structure):
    """Payload: G grasps, each a gripper pose (POSE_LEN) ‖ opening width (m),
    share of hypotheses it is valid under, score (shared/contracts/src/grasps.rs)."""

    _fields_ = [("header", Header), ("grasp_count", ctypes.c_uint32), ("hypothesis_count", ctypes.c_uint32)]

    @staticmethod
    def type_name():
        return "poseflow/Grasps/v1"

    def payload_len(self):
        return GRASP_LEN * self.grasp_count


class TensorHeader(ctypes.Structure):
    """Payload: a row-major f32 tensor of `shape[:rank]` (shared/contracts/src/tensor.rs)."""

    _fields_ = [
        ("header", Header),
        ("shape", ctypes.c_uint32 * 4),
        ("rank", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name():
        return "poseflow/Tensor/v1"

    def payload_len(self):
        n = 1
        for d in self.shape[: self.rank]:
            n *= d
        return n


class NextViewHeader(ctypes.Structure):
    """The chosen next camera pose (POSE_LEN) and the candidates scored
    (payload: C·13, pose ‖ expected rotation trace;
    shared/contracts/src/next_view.rs)."""

    _fields_ = [
        ("header", Header),
        ("chosen", ctypes.c_float * POSE_LEN),
        ("expected_rotation_trace", ctypes.c_float),
        ("current_rotation_trace", ctypes.c_float),
        ("candidate_count", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name():
        return "poseflow/NextView/v1"

    def payload_len(self):
        return CANDIDATE_LEN * self.candidate_count


# Every contract's mirror; tests/e2e/python.rs checks each against the Rust
# layout (size, alignment, field offsets) and iceoryx2 type name.
CONTRACTS = [
    StageStamps,
    Header,
    CameraIntrinsics,
    ObjectCategory,
    FrameHeader,
    ObservationHeader,
    ConditionHandle,
    VelocitySegment,
    VelocityRequest,
    VelocityResponse,
    HypothesesHeader,
    EstimateHeader,
    GraspsHeader,
    Heartbeat,
    TensorHeader,
    NextViewHeader,
]


def monotonic_ns():
    return time.clock_gettime_ns(time.CLOCK_MONOTONIC)


def stamp_clock_ns():
    """The clock of message stamps: CLOCK_REALTIME, ns since the UNIX epoch."""
    return time.clock_gettime_ns(time.CLOCK_REALTIME)


def _float_view(payload):
    """A ctypes float array over a `Slice[c_float]` payload, in place.

    The 0.10 Python bindings report a slice's `len()` in bytes (measured:
    `loan_slice_uninit(5)` of `c_float` has `len() == 20`)."""
    count = payload.len() // ctypes.sizeof(ctypes.c_float)
    return (ctypes.c_float * count).from_address(payload.as_ptr())


def wiring():
    text = os.environ.get("POSEFLOW_STAGE")
    if text is None:
        raise SystemExit("POSEFLOW_STAGE is not set: stages are started by `poseflow run --graph FILE`")
    return json.loads(text)


def _open_pubsub(node, edge, header_type):
    return (
        node.service_builder(iox2.ServiceName.new(edge["service"]))
        .publish_subscribe(iox2.Slice[ctypes.c_float])
        .user_header(header_type)
        .subscriber_max_buffer_size(edge["queue"])
        .history_size(0)
        .enable_safe_overflow(edge["overflow"] == "drop-oldest")
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
    )


def _open_event(node, name):
    return (
        node.service_builder(iox2.ServiceName.new(name))
        .event()
        .max_notifiers(MAX_SUBSCRIBERS)
        .max_listeners(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .event_id_max_value(EVENT_ID_MAX)
        .notifier_created_event(iox2.EventId.new(PUBLISHER_CONNECTED))
        .open_or_create()
    )


class Input:
    """The receiving end of an edge."""

    def __init__(self, node, edge, header_type):
        self.header_type = header_type
        self.subscriber = _open_pubsub(node, edge, header_type).subscriber_builder().buffer_size(edge["queue"]).create()
        self.listener = _open_event(node, edge["service"]).listener_builder().create()
        self.ack = _open_event(node, edge["service"] + "/ack").notifier_builder().create()
        self.connect()

    def connect(self):
        self.subscriber.has_samples()  # touches the port: connects to new publishers
        self.ack.notify_with_custom_event_id(iox2.EventId.new(READY))

    def take_events(self):
        """Returns True once END_OF_STREAM arrived."""
        ids = {activation.id.as_value for activation in self.listener.try_wait()}
        if PUBLISHER_CONNECTED in ids:
            self.connect()
        return END_OF_STREAM in ids

    def receive(self):
        """Yields (header, floats) for every queued message; floats is a ctypes array view."""
        while True:
            sample = self.subscriber.receive()
            if sample is None:
                return
            header = sample.user_header().contents
            floats = _float_view(sample.payload())
            yield header, floats, sample

    def acknowledge_end(self):
        self.ack.notify_with_custom_event_id(iox2.EventId.new(END_ACKNOWLEDGED))


class Output:
    """The sending end of an edge."""

    def __init__(self, node, edge, header_type):
        self.service = _open_pubsub(node, edge, header_type)
        strategy = iox2.BackpressureStrategy.DiscardData if edge["overflow"] == "drop-oldest" else iox2.BackpressureStrategy.RetryUntilDelivered
        self.publisher = (
            self.service.publisher_builder()
            .initial_max_slice_len(max(1, edge["max_payload_len"]))
            .allocation_strategy(iox2.AllocationStrategy.Static)
            .backpressure_strategy(strategy)
            .create()
        )
        self.acks = _open_event(node, edge["service"] + "/ack").listener_builder().create()
        self.notifier = _open_event(node, edge["service"]).notifier_builder().create()

    def _wait_for(self, event_id, count, timeout_s, meanwhile=None, every_s=0.1):
        """Counts `event_id` acks until `count` or `timeout_s`, calling
        `meanwhile` at least every `every_s` (a stage keeps heartbeating)."""
        seen, deadline = 0, time.monotonic() + timeout_s
        while seen < count and time.monotonic() < deadline:
            left = max(0.001, min(every_s, deadline - time.monotonic()))
            for activation in self.acks.timed_wait(iox2.Duration.from_secs_f64(left)):
                if activation.id.as_value == event_id:
                    seen += 1
            if meanwhile is not None:
                meanwhile()
        return seen

    def wait_for_receivers(self, count, timeout_s=10.0, meanwhile=None, every_s=0.1):
        self.publisher.update_connections()
        ready = self._wait_for(READY, count, timeout_s, meanwhile, every_s)
        self.publisher.update_connections()
        return ready

    def publish(self, header, values):
        """Sends `header` (a ctypes structure) with the floats `values` (a sequence)."""
        sample = self.publisher.loan_slice_uninit(len(values))
        ctypes.memmove(sample.user_header_ptr, ctypes.addressof(header), ctypes.sizeof(header))
        _float_view(sample.payload())[:] = values
        sample.assume_init().send()
        self.notifier.notify_with_custom_event_id(iox2.EventId.new(DATA))

    def end_of_stream(self, timeout_s=30.0):
        receivers = self.service.dynamic_config.number_of_subscribers
        self.notifier.notify_with_custom_event_id(iox2.EventId.new(END_OF_STREAM))
        return self._wait_for(END_ACKNOWLEDGED, receivers, timeout_s)


class Counters:
    def __init__(self):
        self.frames_in = self.frames_out = self.dropped = self.errors = 0
        self.last_frame = None
        # Process time per frame, as the Rust runtime reports it: the time
        # spent on a frame's messages, one sample per frame.
        self.latencies_us = []
        self.open_frame = None
        self.open_us = 0

    def received(self, frame_id):
        self.frames_in += 1
        if frame_id != self.open_frame:
            self.close_frame()
            self.open_frame = frame_id
        if self.last_frame is not None and frame_id > self.last_frame + 1:
            self.dropped += frame_id - self.last_frame - 1
        self.last_frame = frame_id

    def worked(self, us):
        self.open_us += us

    def close_frame(self):
        if self.open_frame is not None:
            self.latencies_us.append(max(1, self.open_us))
        self.open_frame, self.open_us = None, 0

    def heartbeat(self, state):
        if state == STATE_FINISHED:
            self.close_frame()
        beat = Heartbeat()
        beat.header.frame_id = self.last_frame or 0
        beat.header.stamps.ns[0] = monotonic_ns()
        beat.pid, beat.state = os.getpid(), state
        beat.frames_in, beat.frames_out, beat.dropped, beat.errors = self.frames_in, self.frames_out, self.dropped, self.errors
        recent = sorted(self.latencies_us[-1000:])
        if recent:
            beat.latency_p50_us = recent[len(recent) // 2]
            beat.latency_p99_us = recent[min(len(recent) - 1, (len(recent) * 99) // 100)]
        return beat


class _Stage:
    """What every stage kind shares: its wiring, node, heartbeat and counters."""

    def __init__(self, kind, inputs, outputs):
        self.wire = wiring()
        got = (len(self.wire["inputs"]), len(self.wire["outputs"]))
        if got != (inputs, outputs):
            raise SystemExit(
                f"stage `{self.wire['stage']}`: a {kind} has {inputs} input(s) and {outputs} output(s); "
                f"the graph gives {got[0]} and {got[1]}"
            )
        self.params = self.wire.get("params") or {}
        self.node = iox2.NodeBuilder.new().name(iox2.NodeName.new(self.wire["stage"])).create(iox2.ServiceType.Ipc)
        beat_edge = {"service": self.wire["heartbeat_service"], "queue": 1, "overflow": "drop-oldest", "max_payload_len": 1}
        self.heartbeat = Output(self.node, beat_edge, Heartbeat)
        self.counters = Counters()
        self.heartbeat.publish(self.counters.heartbeat(STATE_RUNNING), [])

    def output(self, header_type):
        out = Output(self.node, self.wire["outputs"][0], header_type)
        # Heartbeat while readers connect: the supervisor would take a
        # silent wait for a hang.
        every_s = self.wire["heartbeat_ms"] / 1000.0
        out.wait_for_receivers(self.wire["outputs"][0]["readers"], meanwhile=self.beat, every_s=every_s)
        return out

    def beat(self):
        self.heartbeat.publish(self.counters.heartbeat(STATE_RUNNING), [])

    def run_input(self, header_type, handle):
        """Hands every message of the one input to `handle(header, floats)`
        (a contract-breaking one is counted as an error) until end-of-stream
        (returns True) or SIGINT/SIGTERM (returns False)."""
        source = Input(self.node, self.wire["inputs"][0], header_type)
        waitset = iox2.WaitSetBuilder.new().create(iox2.ServiceType.Ipc)
        input_guard = waitset.attach_notification(source.listener)
        beat_guard = waitset.attach_interval(iox2.Duration.from_millis(self.wire["heartbeat_ms"]))
        ended = False
        while not ended:
            attachments, result = waitset.wait_and_process()
            if result in (iox2.WaitSetRunResult.TerminationRequest, iox2.WaitSetRunResult.Interrupt):
                break
            for attachment in attachments:
                if attachment.has_event_from(beat_guard):
                    self.beat()
                if attachment.has_event_from(input_guard):
                    ended = source.take_events()
                    for header, floats, _sample in source.receive():
                        if len(floats) != header.payload_len():
                            self.counters.errors += 1
                            continue
                        self.counters.received(header.header.frame_id)
                        started = time.perf_counter()
                        handle(header, floats)
                        self.counters.worked(int((time.perf_counter() - started) * 1e6) + 1)
        self.source = source
        return ended

    def finish(self):
        self.heartbeat.publish(self.counters.heartbeat(STATE_FINISHED), [])
        self.heartbeat.end_of_stream(1.0)


def _stamp_slot(stage, default):
    """The slot the stage writes: its graph entry's `stamp`, else `default`."""
    stamp = stage.wire.get("stamp")
    if stamp is None:
        return default
    return None if stamp == "none" else SLOT_NAMES.index(stamp)


def _stamped(header, slot):
    if slot is not None:
        header.header.stamps.ns[slot] = stamp_clock_ns()
    return header


def run_transform(process, header_type=HypothesesHeader, slot=SLOT_SAMPLER, output_type=None):
    """Runs `process(header, floats) -> (header, values) or None` as a one-input,
    one-output stage until end-of-stream or SIGINT/SIGTERM. Inputs are
    `header_type` messages, outputs `output_type` ones (default: the same).
    `slot` is the timestamp slot the stage writes on its outputs (None: none)
    unless its graph entry names a `stamp`."""
    stage = _Stage("transform", 1, 1)
    slot = _stamp_slot(stage, slot)
    sink = stage.output(output_type or header_type)

    def handle(header, floats):
        out = process(header, floats)
        if out is not None:
            out_header, values = out
            sink.publish(_stamped(out_header, slot), values)
            stage.counters.frames_out += 1

    if stage.run_input(header_type, handle):
        sink.end_of_stream()
        stage.source.acknowledge_end()
    stage.finish()


def run_sink(consume, header_type):
    """Runs `consume(header, floats)` on every message of the one input until
    end-of-stream or SIGINT/SIGTERM. `floats` is a view into shared memory,
    valid during the call only: copy what you keep (`list(floats)`)."""
    stage = _Stage("sink", 1, 0)
    if stage.run_input(header_type, consume):
        stage.source.acknowledge_end()
    stage.finish()


def run_source(produce, header_type, slot=SLOT_SOURCE):
    """Publishes `produce() -> (header, values)` until it returns None (the
    end of the stream) or SIGINT/SIGTERM. The stage's `rate_hz` parameter,
    when set, paces it; otherwise it sends as fast as its readers take.
    `slot` is the timestamp slot it writes unless its graph entry names a
    `stamp`."""
    stage = _Stage("source", 0, 1)
    slot = _stamp_slot(stage, slot)
    out = stage.output(header_type)
    stop = []
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.append(True))
    rate_hz = float(stage.params.get("rate_hz", 0.0) or 0.0)
    period = 1.0 / rate_hz if rate_hz > 0 else 0.0
    next_send, next_beat = time.monotonic(), time.monotonic()
    beat_every = stage.wire["heartbeat_ms"] / 1000.0
    while not stop:
        if period:
            time.sleep(max(0.0, next_send - time.monotonic()))
            next_send += period
        message = produce()
        if message is None:
            break
        header, values = message
        out.publish(_stamped(header, slot), values)
        stage.counters.frames_out += 1
        if time.monotonic() >= next_beat:
            stage.beat()
            next_beat = time.monotonic() + beat_every
    out.end_of_stream()
    stage.finish()


def estimate_dict(header, floats):
    """An Estimate as plain Python: what a robot program reads.

    `modes` carry their `weight` (share of the samples), `kept` hypotheses
    their selection `score` (best first). Poses are object-to-camera (`x_cam = R x_obj + t`), `R` a 3×3 list of
    rows, `t` in metres, camera frame (OpenCV axes). `covariance` is the 6×6
    tangent covariance at `mean`, order [t; ω] (m², rad²)."""

    def pose(values):
        values = list(values)
        return {"R": [values[0:3], values[3:6], values[6:9]], "t": values[9:12]}

    def weighted(start, count, key):
        records = []
        for i in range(count):
            at = start + i * WEIGHTED_POSE_LEN
            record = pose(floats[at : at + POSE_LEN])
            record[key] = float(floats[at + POSE_LEN])
            records.append(record)
        return records

    modes = header.mode_count
    cov = list(header.covariance)
    return {
        "frame": header.header.frame_id,
        "object": header.header.object_id,
        "best": pose(header.best),
        "mean": pose(header.mean),
        "covariance": [cov[6 * r : 6 * r + 6] for r in range(6)],
        "rotation_trace_rad2": float(header.rotation_trace),
        "selection": SELECTION_METHODS.get(header.selection, header.selection),
        "refined": bool(header.refined),
        "modes": weighted(0, modes, "weight"),
        "kept": weighted(WEIGHTED_POSE_LEN * modes, header.kept_count, "score"),
        "hypotheses": header.hypothesis_count,
    }
