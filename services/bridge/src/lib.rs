//! The Zenoh bridge: one process per host that carries a graph's
//! cross-host edges.
//!
//! `poseflow run --graph G --host NAME` starts it beside that host's stages
//! and supervises it like one. Its wiring's `inputs` are the edges written
//! here and read on other hosts (it subscribes to them over iceoryx2 and
//! puts each message on Zenoh); its `outputs` are the edges written
//! elsewhere and read here (it subscribes on Zenoh and publishes each
//! message into iceoryx2 for the local readers). `params` is the
//! [`BridgePlan`]. Messages travel in the [`wire`] format under
//! `<key_prefix>/data/<edge>`.
//!
//! Start-up keeps the local guarantee that no message is published before
//! its readers are connected: a receiving bridge declares the liveliness
//! token `<key_prefix>/ready/<edge>/<host>` once its own local readers are
//! connected, and a sending bridge subscribes to the edge (which lets the
//! writer start) only when every reading host's token is alive.
//!
//! `block` edges put with Zenoh's blocking congestion control, so a full
//! queue on the far host slows the writer as it would locally;
//! `drop-oldest` edges drop under congestion and keep the newest messages
//! in a ring. Messages lost on the way show as frame-id gaps, counted as
//! `dropped` by this bridge's heartbeat and by the stages downstream.
//! End-of-stream crosses as a marker sample. Restart notices
//! (`UPSTREAM_RESTARTED`) are header flags and cross unchanged.

pub mod netns;
pub mod wire;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::prelude::{CallbackProgression, WaitSetBuilder};
use poseflow_graph::{BridgePlan, EdgeWiring, OverflowPolicy, StageWiring, ZenohMode};
use poseflow_runtime::{ProcessHeartbeat, RuntimeError};
use poseflow_transport::{
    Ipc, TransportError, UntypedPublisher, create_node, termination_requested, untyped_publisher, untyped_subscriber,
};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use crate::wire::WireMessage;

/// How long the far side gets to drain an edge after its end-of-stream.
const END_OF_STREAM_TIMEOUT: Duration = Duration::from_secs(30);
/// How often waits check for SIGINT/SIGTERM.
const POLL: Duration = Duration::from_millis(50);
/// How often a waiting bridge says what it waits for.
const WARN_EVERY: Duration = Duration::from_secs(10);

#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error(transparent)]
    Wiring(#[from] poseflow_graph::WiringError),
    #[error("the stage wiring's params are not a bridge plan")]
    Plan(#[source] serde_json::Error),
    #[error("zenoh: {operation} `{target}`: {detail}")]
    Zenoh { operation: &'static str, target: String, detail: String },
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error(transparent)]
    Runtime(#[from] RuntimeError),
    #[error("the thread receiving edge `{0}` panicked")]
    Panicked(String),
    #[error("waitset")]
    WaitSet(#[source] Box<dyn std::error::Error + Send + Sync>),
}

fn zenoh_error(operation: &'static str, target: &str) -> impl FnOnce(zenoh::Error) -> BridgeError {
    let target = target.to_string();
    move |err| BridgeError::Zenoh { operation, target, detail: err.to_string() }
}

/// What the bridge moved, in both directions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BridgeCounts {
    /// Messages put on Zenoh.
    pub sent: u64,
    /// Messages received from Zenoh and published here.
    pub received: u64,
    /// Frames missing between received messages (frame-id gaps).
    pub lost: u64,
    /// Samples refused: not in the wire format, or failing the contract.
    pub refused: u64,
}

#[derive(Debug, Default)]
struct Counters {
    sent: AtomicU64,
    received: AtomicU64,
    lost: AtomicU64,
    refused: AtomicU64,
}

impl Counters {
    fn snapshot(&self) -> BridgeCounts {
        BridgeCounts {
            sent: self.sent.load(Ordering::Relaxed),
            received: self.received.load(Ordering::Relaxed),
            lost: self.lost.load(Ordering::Relaxed),
            refused: self.refused.load(Ordering::Relaxed),
        }
    }
}

/// The key expression of an edge's messages.
pub fn data_key(prefix: &str, edge: &str) -> String {
    format!("{prefix}/data/{edge}")
}

/// The liveliness token a host declares once it is ready to receive `edge`.
pub fn ready_key(prefix: &str, edge: &str, host: &str) -> String {
    format!("{prefix}/ready/{edge}/{host}")
}

/// The Zenoh configuration of `plan`'s host: its mode, endpoints and
/// scouting.
pub fn zenoh_config(plan: &BridgePlan) -> Result<zenoh::Config, BridgeError> {
    let mode = match plan.zenoh.mode {
        ZenohMode::Peer => "peer",
        ZenohMode::Client => "client",
    };
    let mut connect = plan.endpoints.connect.clone();
    connect.extend(plan.zenoh.router.iter().cloned());
    session_config(mode, &connect, &plan.endpoints.listen, plan.zenoh.multicast_scouting)
        .map_err(|(key, err)| zenoh_error("configure", key)(err))
}

/// A Zenoh session configuration: `mode` (`peer` or `client`), the
/// endpoints to connect to and listen on, multicast scouting on or off. A
/// peer whose endpoints are not up yet keeps trying in the background
/// rather than failing to open. Errors name the configuration key.
pub fn session_config(
    mode: &str,
    connect: &[String],
    listen: &[String],
    multicast_scouting: bool,
) -> Result<zenoh::Config, (&'static str, zenoh::Error)> {
    let mut config = zenoh::Config::default();
    let json = |value: serde_json::Value| value.to_string();
    for (key, value) in [
        ("mode", json(mode.into())),
        ("connect/endpoints", json(connect.into())),
        ("scouting/multicast/enabled", json(multicast_scouting.into())),
    ] {
        config.insert_json5(key, &value).map_err(|err| (key, err))?;
    }
    if !listen.is_empty() {
        config.insert_json5("listen/endpoints", &json(listen.into())).map_err(|err| ("listen/endpoints", err))?;
    }
    Ok(config)
}

/// The wirings of two bridges carrying one edge from host `a` (which
/// listens on `endpoint`) to host `b`, as `poseflow run --host` makes them:
/// for benchmarks and tests that run bridges without a graph file. `edge`
/// names the edge and its settings; its service and readers are set here,
/// for graph instances `instances.0` (on `a`) and `instances.1` (on `b`,
/// where one reader waits).
pub fn one_edge_wirings(
    edge: &EdgeWiring,
    endpoint: &str,
    key_prefix: &str,
    instances: (&str, &str),
) -> Result<(StageWiring, StageWiring), TransportError> {
    let zenoh = poseflow_graph::ZenohSettings {
        mode: ZenohMode::Peer,
        router: None,
        multicast_scouting: false,
        key_prefix: key_prefix.to_string(),
    };
    let wiring = |host: &str, instance: &str, sends: bool| -> Result<StageWiring, TransportError> {
        let edge = EdgeWiring {
            service: poseflow_transport::edge_service_name(instance, &edge.edge)?,
            readers: usize::from(!sends),
            ..edge.clone()
        };
        let endpoints = match sends {
            true => poseflow_graph::HostEndpoints { listen: vec![endpoint.to_string()], connect: Vec::new() },
            false => poseflow_graph::HostEndpoints { listen: Vec::new(), connect: vec![endpoint.to_string()] },
        };
        let readers = match sends {
            true => [(edge.edge.clone(), vec!["b".to_string()])].into(),
            false => Default::default(),
        };
        let plan = BridgePlan { host: host.to_string(), zenoh: zenoh.clone(), endpoints, readers };
        Ok(StageWiring {
            instance: instance.to_string(),
            stage: poseflow_graph::BRIDGE_STAGE.to_string(),
            inputs: if sends { vec![edge.clone()] } else { Vec::new() },
            outputs: if sends { Vec::new() } else { vec![edge] },
            heartbeat_service: poseflow_transport::heartbeat_service_name(instance, poseflow_graph::BRIDGE_STAGE)?,
            heartbeat_ms: 200,
            params: serde_json::to_value(plan).expect("a bridge plan is plain data"),
            ..Default::default()
        })
    };
    Ok((wiring("a", instances.0, true)?, wiring("b", instances.1, false)?))
}

/// Runs the bridge of the wiring in `POSEFLOW_STAGE`.
pub fn run_from_env() -> Result<BridgeCounts, BridgeError> {
    run(&StageWiring::from_env()?)
}

/// Runs the bridge until every carried edge has ended or SIGINT/SIGTERM.
pub fn run(wiring: &StageWiring) -> Result<BridgeCounts, BridgeError> {
    let plan: BridgePlan = serde_json::from_value(wiring.params.clone()).map_err(BridgeError::Plan)?;
    let beat = Arc::new(ProcessHeartbeat::start(wiring)?);
    let session = zenoh::open(zenoh_config(&plan)?).wait().map_err(zenoh_error("open session for host", &plan.host))?;
    tracing::info!(host = %plan.host, zid = %session.zid(), sends = wiring.inputs.len(), receives = wiring.outputs.len(), "bridge running");
    let counters = Arc::new(Counters::default());
    let stop = Arc::new(AtomicBool::new(false));
    let receivers: Vec<_> = wiring
        .outputs
        .iter()
        .map(|edge| {
            let (session, plan, edge) = (session.clone(), plan.clone(), edge.clone());
            let (beat, counters, stop) = (beat.clone(), counters.clone(), stop.clone());
            let name = edge.edge.clone();
            let handle = std::thread::spawn(move || receive(&session, &plan, &edge, &beat, &counters, &stop));
            (name, handle)
        })
        .collect();
    let sending = send(&session, &plan, &wiring.inputs, &beat, &counters, &stop);
    // Sending ended by a failure or a signal: the receivers stop too.
    if sending.is_err() || termination_requested() {
        stop.store(true, Ordering::Relaxed);
    }
    let mut result = sending;
    for (edge, handle) in receivers {
        let received = handle.join().unwrap_or_else(|_| Err(BridgeError::Panicked(edge)));
        result = result.and(received);
    }
    if let Some(beat) = Arc::into_inner(beat) {
        beat.finish();
    }
    let _ = session.close().wait();
    result.map(|()| counters.snapshot())
}

/// Waits until every host reading each of `edges` has declared itself
/// ready for it; false when told to stop first.
fn wait_for_reading_hosts(
    session: &zenoh::Session,
    plan: &BridgePlan,
    edges: &[EdgeWiring],
) -> Result<bool, BridgeError> {
    let prefix = &plan.zenoh.key_prefix;
    let started = Instant::now();
    let mut warned = Instant::now();
    for edge in edges {
        let expected = plan.readers.get(&edge.edge).cloned().unwrap_or_default();
        loop {
            let pattern = format!("{prefix}/ready/{}/*", edge.edge);
            let replies =
                session.liveliness().get(&pattern).wait().map_err(zenoh_error("query liveliness", &pattern))?;
            let mut ready = std::collections::BTreeSet::new();
            while let Ok(reply) = replies.recv() {
                if let Ok(sample) = reply.result()
                    && let Some(host) = sample.key_expr().as_str().rsplit('/').next()
                {
                    ready.insert(host.to_string());
                }
            }
            let missing: Vec<&String> = expected.iter().filter(|h| !ready.contains(*h)).collect();
            if missing.is_empty() {
                break;
            }
            if termination_requested() {
                return Ok(false);
            }
            if warned.elapsed() >= WARN_EVERY {
                tracing::warn!(edge = %edge.edge, ?missing, waited_s = started.elapsed().as_secs(), "waiting for the reading hosts' bridges");
                warned = Instant::now();
            }
            std::thread::sleep(POLL);
        }
    }
    Ok(true)
}

/// Carries the edges written on this host to Zenoh.
fn send(
    session: &zenoh::Session,
    plan: &BridgePlan,
    edges: &[EdgeWiring],
    beat: &ProcessHeartbeat,
    counters: &Counters,
    stop: &AtomicBool,
) -> Result<(), BridgeError> {
    if edges.is_empty() {
        return Ok(());
    }
    if !wait_for_reading_hosts(session, plan, edges)? {
        return Ok(());
    }
    let node = create_node("zenoh-bridge-send")?;
    let mut inputs = Vec::new();
    for edge in edges {
        let subscriber = untyped_subscriber(&node, &edge.message, &edge.service, &edge.options())?;
        let key = data_key(&plan.zenoh.key_prefix, &edge.edge);
        let congestion = match edge.overflow {
            OverflowPolicy::Block => CongestionControl::Block,
            OverflowPolicy::DropOldest => CongestionControl::Drop,
        };
        let publisher = session
            .declare_publisher(key.clone())
            .congestion_control(congestion)
            .express(true)
            .wait()
            .map_err(zenoh_error("declare publisher", &key))?;
        inputs.push((edge, subscriber, publisher));
    }
    tracing::info!(edges = ?edges.iter().map(|e| &e.edge).collect::<Vec<_>>(), "sending");
    let waitset = WaitSetBuilder::new().create::<Ipc>().map_err(|e| BridgeError::WaitSet(Box::new(e)))?;
    let guards = inputs
        .iter()
        .map(|(_, subscriber, _)| waitset.attach_notification(subscriber.as_ref()))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| BridgeError::WaitSet(Box::new(e)))?;
    // Wakes the loop to notice `stop` while no message comes.
    let _tick = waitset.attach_interval(POLL).map_err(|e| BridgeError::WaitSet(Box::new(e)))?;
    let mut ended = vec![false; inputs.len()];
    let mut failure = None;
    let forward = |i: usize| -> Result<bool, BridgeError> {
        let (edge, subscriber, publisher) = &inputs[i];
        let end = subscriber.take_events()?;
        loop {
            let mut bytes = None;
            if !subscriber.receive_with(&mut |header, payload| bytes = Some(wire::encode_message(header, payload)))? {
                break;
            }
            beat.received();
            if let Some(bytes) = bytes {
                publisher.put(bytes).wait().map_err(zenoh_error("put on", &edge.edge))?;
                counters.sent.fetch_add(1, Ordering::Relaxed);
                beat.sent();
            }
        }
        if end {
            publisher.put(wire::encode_end()).wait().map_err(zenoh_error("end the stream on", &edge.edge))?;
            subscriber.acknowledge_end()?;
            tracing::info!(edge = %edge.edge, "end of stream sent");
        }
        Ok(end)
    };
    waitset
        .wait_and_process(|id| {
            for (i, guard) in guards.iter().enumerate() {
                if id.has_event_from(guard) {
                    match forward(i) {
                        Ok(end) => ended[i] |= end,
                        Err(err) => {
                            failure = Some(err);
                            return CallbackProgression::Stop;
                        }
                    }
                }
            }
            let finished = ended.iter().all(|e| *e);
            if finished || stop.load(Ordering::Relaxed) {
                CallbackProgression::Stop
            } else {
                CallbackProgression::Continue
            }
        })
        .map_err(|e| BridgeError::WaitSet(Box::new(e)))?;
    failure.map_or(Ok(()), Err)
}

/// A Zenoh subscriber with the queue an edge's overflow policy calls for.
enum Incoming {
    /// `block`: a full queue holds up the network link (back-pressure).
    Fifo(zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>),
    /// `drop-oldest`: the newest `queue` samples are kept.
    Ring(zenoh::pubsub::Subscriber<zenoh::handlers::RingChannelHandler<zenoh::sample::Sample>>),
}

impl Incoming {
    fn next(&self, timeout: Duration) -> zenoh::Result<Option<zenoh::sample::Sample>> {
        match self {
            Self::Fifo(subscriber) => subscriber.recv_timeout(timeout),
            Self::Ring(subscriber) => subscriber.recv_timeout(timeout),
        }
    }
}

/// Carries one edge written on another host into this host's iceoryx2.
fn receive(
    session: &zenoh::Session,
    plan: &BridgePlan,
    edge: &EdgeWiring,
    beat: &ProcessHeartbeat,
    counters: &Counters,
    stop: &AtomicBool,
) -> Result<(), BridgeError> {
    // iceoryx2 ports belong to the thread that made them.
    let node = create_node(&format!("zenoh-bridge-{}", edge.edge))?;
    let publisher = untyped_publisher(&node, &edge.message, &edge.service, &edge.options())?;
    publisher.wait_for_all_receivers(edge.readers, WARN_EVERY)?;
    let key = data_key(&plan.zenoh.key_prefix, &edge.edge);
    let builder = session.declare_subscriber(key.clone());
    let incoming = match edge.overflow {
        OverflowPolicy::Block => Incoming::Fifo(
            builder
                .with(zenoh::handlers::FifoChannel::new(edge.queue))
                .wait()
                .map_err(zenoh_error("subscribe to", &key))?,
        ),
        OverflowPolicy::DropOldest => Incoming::Ring(
            builder
                .with(zenoh::handlers::RingChannel::new(edge.queue))
                .wait()
                .map_err(zenoh_error("subscribe to", &key))?,
        ),
    };
    let ready = ready_key(&plan.zenoh.key_prefix, &edge.edge, &plan.host);
    let _token = session.liveliness().declare_token(ready.clone()).wait().map_err(zenoh_error("declare", &ready))?;
    tracing::info!(edge = %edge.edge, "receiving");
    let mut last_frame: Option<u64> = None;
    while !stop.load(Ordering::Relaxed) && !termination_requested() {
        let Some(sample) = incoming.next(POLL).map_err(zenoh_error("receive on", &key))? else { continue };
        let bytes = sample.payload().to_bytes();
        match wire::decode(&bytes) {
            Ok(WireMessage::EndOfStream) => {
                tracing::info!(edge = %edge.edge, "end of stream received");
                publisher.end_of_stream(END_OF_STREAM_TIMEOUT)?;
                return Ok(());
            }
            Ok(WireMessage::Message { header, payload }) => {
                beat.received();
                publish(publisher.as_ref(), header, &payload, &mut last_frame, beat, counters);
            }
            Err(err) => {
                counters.refused.fetch_add(1, Ordering::Relaxed);
                beat.error();
                tracing::warn!(edge = %edge.edge, %err, "sample refused");
            }
        }
    }
    Ok(())
}

/// Publishes one received message, counting frame-id gaps as lost frames
/// and contract failures as refused messages.
fn publish(
    publisher: &dyn UntypedPublisher,
    header: &[u8],
    payload: &[f32],
    last_frame: &mut Option<u64>,
    beat: &ProcessHeartbeat,
    counters: &Counters,
) {
    match publisher.publish_bytes(header, payload) {
        Ok(common) => {
            let frame = common.frame_id;
            let _span = tracing::debug_span!("bridge", frame).entered();
            // A smaller id means the source restarted its numbering, not a loss.
            if let Some(last) = *last_frame
                && frame > last + 1
            {
                let missing = frame - last - 1;
                counters.lost.fetch_add(missing, Ordering::Relaxed);
                beat.dropped(missing);
                tracing::warn!(edge = publisher.edge(), frame, missing, "frames missing on the way between hosts");
            }
            *last_frame = Some(frame);
            counters.received.fetch_add(1, Ordering::Relaxed);
            beat.sent();
        }
        Err(err) => {
            counters.refused.fetch_add(1, Ordering::Relaxed);
            beat.error();
            tracing::warn!(edge = publisher.edge(), %err, "message refused");
        }
    }
}
