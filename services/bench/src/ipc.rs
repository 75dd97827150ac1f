//! One-way latency per hop, measured on real traffic: the sender stamps
//! `CLOCK_MONOTONIC` when the message is ready to go, the receiver when it
//! holds a usable message; the clock is shared by all processes of a
//! machine. iceoryx2 and the Unix socket cross processes (the receiver is a
//! child `poseflow bench ipc-receive`); the channel baseline crosses threads.
//!
//! With `--zenoh`, one more path: an edge between two hosts, simulated by
//! two network namespaces joined by a veth pair (created for the run; it
//! needs root). The sender publishes over iceoryx2 on host A, A's Zenoh
//! bridge puts the message on the link, B's bridge publishes it over
//! iceoryx2 to the receiver on B: the whole hop a graph's cross-host edge
//! takes. The namespaces share this machine's clock.

use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use hdrhistogram::Histogram;
use iceoryx2::prelude::{CallbackProgression, WaitSetBuilder};
use poseflow_bridge::netns::{ADDRESS_A, HostPair};
use poseflow_contracts::{Header, MessageHeader, TensorHeader, monotonic_ns};
use poseflow_graph::{BRIDGE_EXE, EdgeWiring, OverflowPolicy, WIRING_ENV};
use poseflow_transport::{EdgeOptions, EdgeSubscriber, Ipc, Overflow, Publisher, create_node, edge_service_name};
use serde::{Deserialize, Serialize};
use serde_json::json;

const PAYLOAD_BYTES: [usize; 4] = [4 << 10, 64 << 10, 1 << 20, 4 << 20];

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Transport {
    Iceoryx2,
    InProcess,
    UnixSocketBincode,
    ZenohTwoHosts,
}

impl Transport {
    fn name(self) -> &'static str {
        match self {
            Transport::Iceoryx2 => "iceoryx2",
            Transport::InProcess => "in_process",
            Transport::UnixSocketBincode => "unix_socket_bincode",
            Transport::ZenohTwoHosts => "zenoh_two_hosts",
        }
    }
}

#[derive(Debug, Args)]
pub struct IpcArgs {
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Measured messages per transport and payload size.
    #[arg(long, default_value_t = 1000)]
    pub samples: u32,
    /// Unmeasured messages sent first (page faults, connection set-up).
    #[arg(long, default_value_t = 100)]
    pub warmup: u32,
    /// Pause between messages, microseconds, so each is measured on an idle
    /// path rather than behind a queue.
    #[arg(long, default_value_t = 1000)]
    pub period_us: u64,
    /// Also measure an edge between two hosts through the Zenoh bridges,
    /// with two network namespaces standing in for the hosts (needs root
    /// and `ip`).
    #[arg(long)]
    pub zenoh: bool,
}

#[derive(Debug, Args)]
pub struct ReceiveArgs {
    #[arg(long, value_enum)]
    pub transport: Transport,
    /// iceoryx2 service name or Unix socket path.
    #[arg(long)]
    pub address: String,
    #[arg(long)]
    pub payload_bytes: usize,
    #[arg(long)]
    pub messages: u32,
    #[arg(long)]
    pub warmup: u32,
}

/// Latency quantiles of one transport and payload size, microseconds.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Summary {
    p50_us: f64,
    p90_us: f64,
    p99_us: f64,
    max_us: f64,
    samples: u64,
}

fn histogram() -> Histogram<u64> {
    // 100 ns .. 10 s, 3 significant digits.
    Histogram::new_with_bounds(100, 10_000_000_000, 3).expect("valid histogram bounds")
}

fn summarize(h: &Histogram<u64>) -> Summary {
    let us = |ns: u64| ns as f64 / 1000.0;
    Summary {
        p50_us: us(h.value_at_quantile(0.5)),
        p90_us: us(h.value_at_quantile(0.9)),
        p99_us: us(h.value_at_quantile(0.99)),
        max_us: us(h.max()),
        samples: h.len(),
    }
}

/// A message as the socket baseline carries it.
#[derive(Serialize, Deserialize)]
struct WireMessage {
    frame_id: u64,
    sent_ns: u64,
    payload: Vec<f32>,
}

pub fn run(args: &IpcArgs) -> anyhow::Result<()> {
    let mut results = serde_json::Map::new();
    let mut transports = vec![Transport::Iceoryx2, Transport::InProcess, Transport::UnixSocketBincode];
    let hosts = match args.zenoh {
        true => {
            transports.push(Transport::ZenohTwoHosts);
            Some(
                HostPair::create("pfb")
                    .map_err(|reason| anyhow::anyhow!("--zenoh needs two network namespaces: {reason}"))?,
            )
        }
        false => None,
    };
    for transport in transports {
        let mut per_size = serde_json::Map::new();
        for bytes in PAYLOAD_BYTES {
            let summary = measure(transport, bytes, args, hosts.as_ref())
                .with_context(|| format!("{} at {bytes} bytes", transport.name()))?;
            tracing::info!(
                transport = transport.name(),
                bytes,
                p50_us = summary.p50_us,
                p99_us = summary.p99_us,
                "measured"
            );
            per_size.insert(bytes.to_string(), serde_json::to_value(summary)?);
        }
        results.insert(transport.name().to_string(), per_size.into());
    }
    if let Some(ratios) = zenoh_ratios(&results) {
        results.insert("zenoh_4mib_p50_ratio".into(), ratios);
    }
    if args.json {
        println!("{}", serde_json::Value::Object(results));
    } else {
        println!("{}", table(&results, args));
    }
    Ok(())
}

/// The two-host hop's p50 at 4 MiB against local iceoryx2 and the Unix
/// socket, measured in the same run.
fn zenoh_ratios(results: &serde_json::Map<String, serde_json::Value>) -> Option<serde_json::Value> {
    let p50 = |transport: Transport| results.get(transport.name())?[(4usize << 20).to_string()]["p50_us"].as_f64();
    let zenoh = p50(Transport::ZenohTwoHosts)?;
    Some(json!({
        "vs_iceoryx2": zenoh / p50(Transport::Iceoryx2)?,
        "vs_unix_socket": zenoh / p50(Transport::UnixSocketBincode)?,
    }))
}

fn table(results: &serde_json::Map<String, serde_json::Value>, args: &IpcArgs) -> String {
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let mut out = format!(
        "one-way latency per hop, µs ({} samples after {} warm-up, one message every {} µs, {cores} cores)\n",
        args.samples, args.warmup, args.period_us
    );
    out.push_str(&format!(
        "{:<21} {:>9} {:>9} {:>9} {:>9} {:>9}\n",
        "transport", "payload", "p50", "p90", "p99", "max"
    ));
    for (transport, sizes) in results.iter().filter(|(name, _)| !name.ends_with("ratio")) {
        for bytes in PAYLOAD_BYTES {
            let s = &sizes[bytes.to_string()];
            let size = if bytes >= 1 << 20 { format!("{} MiB", bytes >> 20) } else { format!("{} KiB", bytes >> 10) };
            out.push_str(&format!(
                "{transport:<21} {size:>9} {:>9.1} {:>9.1} {:>9.1} {:>9.1}\n",
                s["p50_us"].as_f64().unwrap_or(f64::NAN),
                s["p90_us"].as_f64().unwrap_or(f64::NAN),
                s["p99_us"].as_f64().unwrap_or(f64::NAN),
                s["max_us"].as_f64().unwrap_or(f64::NAN),
            ));
        }
    }
    if let Some(ratios) = results.get("zenoh_4mib_p50_ratio") {
        out.push_str(&format!(
            "two hosts over Zenoh at 4 MiB, p50: {:.1}x local iceoryx2, {:.1}x a Unix socket\n",
            ratios["vs_iceoryx2"].as_f64().unwrap_or(f64::NAN),
            ratios["vs_unix_socket"].as_f64().unwrap_or(f64::NAN)
        ));
    }
    out
}

fn measure(transport: Transport, bytes: usize, args: &IpcArgs, hosts: Option<&HostPair>) -> anyhow::Result<Summary> {
    let messages = args.warmup + args.samples;
    let period = Duration::from_micros(args.period_us);
    match transport {
        Transport::InProcess => Ok(in_process(bytes, messages, args.warmup, period)),
        Transport::Iceoryx2 => {
            let address = edge_service_name(&format!("bench-{}", std::process::id()), &format!("ipc-{bytes}"))?;
            let child = spawn_receiver(transport, &address, bytes, messages, args.warmup, None)?;
            send_iceoryx2(&address, bytes, messages, period)?;
            child.finish()
        }
        Transport::ZenohTwoHosts => {
            let hosts = hosts.expect("namespaces exist with --zenoh");
            let bridges = TwoHostEdge::start(hosts, bytes)?;
            let child = spawn_receiver(
                Transport::Iceoryx2,
                &bridges.receiving_service,
                bytes,
                messages,
                args.warmup,
                Some(&hosts.b),
            )?;
            send_iceoryx2(&bridges.sending_service, bytes, messages, period)?;
            let summary = child.finish();
            bridges.finish()?;
            summary
        }
        Transport::UnixSocketBincode => {
            let path = std::env::temp_dir().join(format!("poseflow-bench-{}-{bytes}.sock", std::process::id()));
            let child = spawn_receiver(transport, &path.display().to_string(), bytes, messages, args.warmup, None)?;
            let result = send_socket(&path, bytes, messages, period);
            let _ = std::fs::remove_file(&path);
            result?;
            child.finish()
        }
    }
}

/// The receiving child process; it prints its summary as JSON and exits.
struct Receiver {
    child: std::process::Child,
}

impl Receiver {
    fn finish(self) -> anyhow::Result<Summary> {
        let output = self.child.wait_with_output()?;
        if !output.status.success() {
            bail!("receiver failed ({})", output.status);
        }
        serde_json::from_slice(&output.stdout).context("receiver summary")
    }
}

/// Starts the receiving process, inside network namespace `namespace` if given.
fn spawn_receiver(
    transport: Transport,
    address: &str,
    bytes: usize,
    messages: u32,
    warmup: u32,
    namespace: Option<&str>,
) -> anyhow::Result<Receiver> {
    let mut command = Command::new(std::env::current_exe()?);
    if let Some(namespace) = namespace {
        command = HostPair::inside(namespace, &command);
    }
    let mut child = command
        .args(["bench", "ipc-receive", "--transport"])
        .arg(transport.to_possible_value().expect("named variant").get_name())
        .args(["--address", address, "--payload-bytes", &bytes.to_string()])
        .args(["--messages", &messages.to_string(), "--warmup", &warmup.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()?;
    // The receiver says "ready" on stderr once it listens.
    let stderr = child.stderr.take().expect("piped");
    let mut lines = BufReader::new(stderr).lines();
    loop {
        match lines.next() {
            Some(Ok(line)) if line.trim() == "ready" => break,
            Some(Ok(_)) => continue,
            _ => bail!("receiver exited before it was ready"),
        }
    }
    // Keep draining its stderr so it never blocks on a full pipe.
    std::thread::spawn(move || for _ in lines {});
    Ok(Receiver { child })
}

fn floats(bytes: usize) -> usize {
    bytes / std::mem::size_of::<f32>()
}

fn send_iceoryx2(address: &str, bytes: usize, messages: u32, period: Duration) -> anyhow::Result<()> {
    let node = create_node("bench-sender")?;
    let options = EdgeOptions { queue: 4, overflow: Overflow::Block, max_payload_len: floats(bytes) };
    let publisher = Publisher::<TensorHeader>::create(&node, address, &options)?;
    // Long enough for two Zenoh bridges to find each other.
    if publisher.wait_for_receivers(1, Duration::from_secs(30))? < 1 {
        bail!("the receiver never connected to {address}");
    }
    let len = floats(bytes);
    for frame in 0..u64::from(messages) {
        std::thread::sleep(period);
        let mut header = TensorHeader::vector(Header::new(frame, 0), len as u32);
        // The payload is written in place in shared memory; only its first
        // value is touched so the measurement is of the transport.
        header.header.stamps.ns[0] = monotonic_ns();
        publisher.publish(header, len, |payload| payload[0] = frame as f32)?;
    }
    publisher.end_of_stream(Duration::from_secs(10))?;
    Ok(())
}

fn send_socket(path: &PathBuf, bytes: usize, messages: u32, period: Duration) -> anyhow::Result<()> {
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut stream = loop {
        match UnixStream::connect(path) {
            Ok(stream) => break stream,
            Err(_) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(5)),
            Err(e) => return Err(e).context("connect to the receiver"),
        }
    };
    let mut payload = vec![0.0f32; floats(bytes)];
    for frame in 0..u64::from(messages) {
        std::thread::sleep(period);
        payload[0] = frame as f32;
        let message = WireMessage { frame_id: frame, sent_ns: monotonic_ns(), payload };
        let encoded = bincode::serde::encode_to_vec(&message, bincode::config::standard())?;
        stream.write_all(&(encoded.len() as u64).to_le_bytes())?;
        stream.write_all(&encoded)?;
        payload = message.payload;
    }
    Ok(())
}

fn in_process(bytes: usize, messages: u32, warmup: u32, period: Duration) -> Summary {
    let (tx, rx) = std::sync::mpsc::sync_channel::<WireMessage>(4);
    let receiver = std::thread::spawn(move || {
        let mut h = histogram();
        for message in rx {
            let latency = monotonic_ns().saturating_sub(message.sent_ns);
            if message.frame_id >= u64::from(warmup) {
                h.saturating_record(latency);
            }
        }
        h
    });
    // Buffers are allocated ahead, as a stage reusing its outputs would.
    let mut spare: Vec<Vec<f32>> = (0..messages).map(|_| vec![0.0f32; floats(bytes)]).collect();
    for frame in 0..u64::from(messages) {
        std::thread::sleep(period);
        let mut payload = spare.pop().expect("one buffer per message");
        payload[0] = frame as f32;
        let _ = tx.send(WireMessage { frame_id: frame, sent_ns: monotonic_ns(), payload });
    }
    drop(tx);
    summarize(&receiver.join().expect("receiver thread"))
}

/// `poseflow bench ipc-receive`: receives, records latency, prints JSON.
pub fn receive(args: &ReceiveArgs) -> anyhow::Result<()> {
    let mut h = histogram();
    match args.transport {
        Transport::Iceoryx2 => receive_iceoryx2(args, &mut h)?,
        Transport::UnixSocketBincode => receive_socket(args, &mut h)?,
        Transport::InProcess | Transport::ZenohTwoHosts => {
            bail!("{} has no receiving process of its own", args.transport.name())
        }
    }
    println!("{}", json!(summarize(&h)));
    Ok(())
}

fn receive_iceoryx2(args: &ReceiveArgs, h: &mut Histogram<u64>) -> anyhow::Result<()> {
    let node = create_node("bench-receiver")?;
    let options = EdgeOptions { queue: 4, overflow: Overflow::Block, max_payload_len: floats(args.payload_bytes) };
    let subscriber = EdgeSubscriber::<TensorHeader>::create(&node, &args.address, &options)?;
    let waitset = WaitSetBuilder::new().create::<Ipc>().map_err(|e| anyhow::anyhow!("{e:?}"))?;
    let guard = waitset.attach_notification(&subscriber).map_err(|e| anyhow::anyhow!("{e:?}"))?;
    eprintln!("ready");
    let mut failure = None;
    let mut ended = false;
    waitset
        .wait_and_process(|id| {
            if !id.has_event_from(&guard) {
                return CallbackProgression::Continue;
            }
            let step = subscriber.take_events().and_then(|end| {
                ended = end;
                while let Some(message) = subscriber.receive()? {
                    let latency = monotonic_ns().saturating_sub(message.header().header.stamps.ns[0]);
                    message.header().check_payload(message.payload())?;
                    if message.header().header.frame_id >= u64::from(args.warmup) {
                        h.saturating_record(latency);
                    }
                }
                Ok(())
            });
            if let Err(err) = step {
                failure = Some(err);
                return CallbackProgression::Stop;
            }
            if ended { CallbackProgression::Stop } else { CallbackProgression::Continue }
        })
        .map_err(|e| anyhow::anyhow!("{e:?}"))?;
    if let Some(err) = failure {
        return Err(err.into());
    }
    subscriber.acknowledge_end()?;
    Ok(())
}

fn receive_socket(args: &ReceiveArgs, h: &mut Histogram<u64>) -> anyhow::Result<()> {
    let listener = UnixListener::bind(&args.address)?;
    eprintln!("ready");
    let (mut stream, _) = listener.accept()?;
    let mut buffer = Vec::new();
    for _ in 0..args.messages {
        let mut len = [0u8; 8];
        stream.read_exact(&mut len)?;
        buffer.resize(u64::from_le_bytes(len) as usize, 0);
        stream.read_exact(&mut buffer)?;
        let (message, _): (WireMessage, usize) =
            bincode::serde::decode_from_slice(&buffer, bincode::config::standard())?;
        let latency = monotonic_ns().saturating_sub(message.sent_ns);
        if message.payload.len() != floats(args.payload_bytes) {
            bail!(
                "message {} holds {} values, expected {}",
                message.frame_id,
                message.payload.len(),
                floats(args.payload_bytes)
            );
        }
        if message.frame_id >= u64::from(args.warmup) {
            h.saturating_record(latency);
        }
    }
    Ok(())
}

/// One edge from host A to host B: a Zenoh bridge process in each
/// namespace, wired as `poseflow run --host` wires them.
struct TwoHostEdge {
    sending_service: String,
    receiving_service: String,
    bridges: Vec<std::process::Child>,
}

impl TwoHostEdge {
    fn start(hosts: &HostPair, bytes: usize) -> anyhow::Result<Self> {
        let exe = poseflow_graph::resolve_executable(BRIDGE_EXE, Path::new("."), &poseflow_launch::search_path(&[]))
            .map_err(|searched| anyhow::anyhow!("no `{BRIDGE_EXE}` executable; looked in {searched:?}"))?;
        let id = format!("{}-{bytes}", std::process::id());
        // A port per payload size: the previous size's listener may linger.
        let port = 7447 + PAYLOAD_BYTES.iter().position(|b| *b == bytes).unwrap_or(0);
        let edge = EdgeWiring {
            edge: "ipc".into(),
            service: String::new(),
            message: TensorHeader::NAME.into(),
            queue: 4,
            overflow: OverflowPolicy::Block,
            max_payload_len: floats(bytes),
            readers: 0,
        };
        let (sending, receiving) = poseflow_bridge::one_edge_wirings(
            &edge,
            &format!("tcp/{ADDRESS_A}:{port}"),
            &format!("poseflow/bench-{id}"),
            (&format!("bench-a-{id}"), &format!("bench-b-{id}")),
        )?;
        let (sending_service, receiving_service) =
            (sending.inputs[0].service.clone(), receiving.outputs[0].service.clone());
        let mut bridges = Vec::new();
        for (wiring, namespace) in [(receiving, &hosts.b), (sending, &hosts.a)] {
            let mut command = Command::new(&exe);
            command.env(WIRING_ENV, wiring.to_json()).env("RUST_LOG", "warn");
            bridges.push(HostPair::inside(namespace, &command).stdin(Stdio::null()).stdout(Stdio::null()).spawn()?);
        }
        Ok(Self { sending_service, receiving_service, bridges })
    }

    /// Waits for both bridges to end after the stream's end; kills any
    /// still running after 10 s.
    fn finish(mut self) -> anyhow::Result<()> {
        let deadline = Instant::now() + Duration::from_secs(10);
        for bridge in &mut self.bridges {
            loop {
                match bridge.try_wait()? {
                    Some(status) if status.success() => break,
                    Some(status) => bail!("a Zenoh bridge failed ({status})"),
                    None if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
                    None => {
                        let _ = bridge.kill();
                        let _ = bridge.wait();
                        bail!("a Zenoh bridge did not end after the stream's end");
                    }
                }
            }
        }
        Ok(())
    }
}
