//! iceoryx2's Zenoh tunnel (iceoryx2-tunnel-zenoh 0.8.1) measured as
//! `poseflow bench ipc --zenoh` measures PoseFlow's bridge: one
//! publish-subscribe service, a tunnel per "host" (network namespace),
//! payloads stamped with CLOCK_MONOTONIC at send and compared on receipt.
//! Each side has its own iceoryx2 prefix, so the two "hosts" do not share
//! services through /dev/shm. The tunnel polls (`propagate` every
//! `poll_us`, discovery every 100 ms); the subscriber polls every 20 µs.
//!
//! `tunnel <prefix> listen|connect <endpoint> <poll_us>`,
//! `pub <prefix> <bytes> <count> <period_ms>`, `sub <prefix> <count> <warmup>`.

use std::time::{Duration, Instant};

use iceoryx2::prelude::*;
use iceoryx2_bb_system_types::file_name::FileName;

fn now_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: a valid timespec; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

fn config(prefix: &str) -> iceoryx2::config::Config {
    let mut config = iceoryx2::config::Config::default();
    config.global.prefix = FileName::new(prefix.as_bytes()).expect("a valid prefix");
    config
}

fn main() {
    set_log_level(LogLevel::Warn);
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize| args.get(i).expect("see the module docs for the arguments").as_str();
    let number = |i: usize| arg(i).parse::<u64>().expect("a number");
    match arg(1) {
        "tunnel" => tunnel(arg(2), arg(3), arg(4), number(5)),
        "pub" => publish(arg(2), number(3) as usize, number(4), number(5)),
        "sub" => subscribe(arg(2), number(3) as usize, number(4) as usize),
        other => panic!("{other}: expected tunnel, pub or sub"),
    }
}

fn tunnel(prefix: &str, role: &str, endpoint: &str, poll_us: u64) {
    let mut zenoh_config = zenoh::Config::default();
    zenoh_config.insert_json5("mode", "\"peer\"").unwrap();
    zenoh_config.insert_json5("scouting/multicast/enabled", "false").unwrap();
    let key = if role == "listen" { "listen/endpoints" } else { "connect/endpoints" };
    zenoh_config.insert_json5(key, &format!("[\"{endpoint}\"]")).unwrap();
    let mut tunnel =
        iceoryx2_tunnel::Tunnel::<ipc::Service, iceoryx2_tunnel_zenoh::ZenohBackend<ipc::Service>>::create(
            &iceoryx2_tunnel::Config::default(),
            &config(prefix),
            &zenoh_config,
        )
        .unwrap();
    let mut discovered = Instant::now() - Duration::from_secs(1);
    loop {
        if discovered.elapsed() > Duration::from_millis(100) {
            tunnel.discover().unwrap();
            discovered = Instant::now();
        }
        tunnel.propagate().unwrap();
        std::thread::sleep(Duration::from_micros(poll_us));
    }
}

type Factory = iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, [u8], ()>;

fn service(node: &Node<ipc::Service>) -> Factory {
    node.service_builder(&"poseflow/tunnel-bench".try_into().unwrap())
        .publish_subscribe::<[u8]>()
        .max_publishers(2)
        .max_subscribers(4)
        .subscriber_max_buffer_size(16)
        .history_size(0)
        .open_or_create()
        .unwrap()
}

fn publish(prefix: &str, size: usize, count: u64, period_ms: u64) {
    let node = NodeBuilder::new().config(&config(prefix)).create::<ipc::Service>().unwrap();
    let service = service(&node);
    let publisher = service.publisher_builder().initial_max_slice_len(size).create().unwrap();
    // Time for both tunnels to discover the service.
    std::thread::sleep(Duration::from_secs(3));
    for _ in 0..count {
        let sample = publisher.loan_slice_uninit(size).unwrap();
        let stamp = now_ns().to_le_bytes();
        let sample = sample.write_from_fn(|k| if k < 8 { stamp[k] } else { k as u8 });
        sample.send().unwrap();
        std::thread::sleep(Duration::from_millis(period_ms));
    }
}

fn subscribe(prefix: &str, count: usize, warmup: usize) {
    let node = NodeBuilder::new().config(&config(prefix)).create::<ipc::Service>().unwrap();
    let service = service(&node);
    let subscriber = service.subscriber_builder().create().unwrap();
    let mut latencies_us = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut seen = 0;
    while seen < count && Instant::now() < deadline {
        match subscriber.receive().unwrap() {
            Some(sample) => {
                let received = now_ns();
                let sent = u64::from_le_bytes(sample.payload()[..8].try_into().unwrap());
                seen += 1;
                if seen > warmup {
                    latencies_us.push((received - sent) / 1000);
                }
            }
            None => std::thread::sleep(Duration::from_micros(20)),
        }
    }
    latencies_us.sort_unstable();
    let quantile = |q: f64| latencies_us.get(((latencies_us.len() as f64 - 1.0) * q) as usize).copied().unwrap_or(0);
    println!("received {seen}/{count}; latency p50 {} us p99 {} us", quantile(0.5), quantile(0.99));
}
