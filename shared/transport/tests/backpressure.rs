//! With `Overflow::Block` a full receiver queue makes the publisher wait, so
//! nothing is lost.

use std::time::Duration;

use poseflow_contracts::{Header, HypothesesHeader, POSE_LEN};
use poseflow_transport::{EdgeOptions, EdgeSubscriber, Overflow, Publisher, create_node, edge_service_name};

/// A thread that publishes frames `0..count` on `name` once `wait` (given
/// its publisher) returns, then ends the stream; joins to what `wait`
/// returned.
fn spawn_sender(
    name: &str,
    options: EdgeOptions,
    count: u64,
    wait: impl FnOnce(&Publisher<HypothesesHeader>) -> usize + Send + 'static,
) -> std::thread::JoinHandle<usize> {
    let name = name.to_string();
    std::thread::spawn(move || {
        let node = create_node("test-sender").unwrap();
        let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &options).unwrap();
        let ready = wait(&publisher);
        for frame in 0..count {
            let header = HypothesesHeader {
                header: Header::new(frame, 1),
                sample_count: 1,
                step_count: 1,
                ..Default::default()
            };
            publisher.publish(header, POSE_LEN, |p| p.fill(frame as f32)).unwrap();
        }
        publisher.end_of_stream(Duration::from_secs(10)).unwrap();
        ready
    })
}

/// The frame ids received until the end of the stream, reading every
/// `pause`; acknowledges the end.
fn receive_until_end(subscriber: &EdgeSubscriber<HypothesesHeader>, pause: Duration) -> Vec<u64> {
    let mut frames = Vec::new();
    loop {
        // Events carry the READY handshake with a new publisher and the end
        // of the stream, which follows the last sample.
        let ended = subscriber.take_events().unwrap();
        while let Some(message) = subscriber.receive().unwrap() {
            frames.push(message.header().header.frame_id);
        }
        if ended {
            break;
        }
        std::thread::sleep(pause);
    }
    subscriber.acknowledge_end().unwrap();
    frames
}

#[test]
fn block_overflow_loses_nothing() {
    let name = edge_service_name(&format!("test-block-{}", std::process::id()), "poses").unwrap();
    let options = EdgeOptions { queue: 16, overflow: Overflow::Block, max_payload_len: 4096 };
    let node = create_node("block-receiver").unwrap();
    let subscriber = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    let sender = spawn_sender(&name, options, 200, |publisher| {
        publisher.wait_for_receivers(1, Duration::from_secs(10)).unwrap()
    });
    // A slow receiver: the sender must wait for it, not drop.
    let frames = receive_until_end(&subscriber, Duration::from_millis(5));
    assert_eq!(sender.join().unwrap(), 1);
    assert_eq!(frames, (0..200).collect::<Vec<_>>());
}

/// A publisher waiting on a full queue runs its `meanwhile` between retries:
/// the receiver here reads only once it has seen that happen, as a client
/// reads its inputs only once the server it waits on has answered.
#[test]
fn a_blocked_publish_keeps_serving_until_the_queue_drains() {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicUsize, Ordering};

    let name = edge_service_name(&format!("test-serving-{}", std::process::id()), "handles").unwrap();
    let options = EdgeOptions { queue: 1, overflow: Overflow::Block, max_payload_len: 64 };
    let node = create_node("serving-receiver").unwrap();
    let subscriber = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    let served = Arc::new(AtomicUsize::new(0));
    let sender = std::thread::spawn({
        let (name, served) = (name.clone(), served.clone());
        move || {
            let node = create_node("serving-sender").unwrap();
            let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &options).unwrap();
            assert_eq!(publisher.wait_for_receivers(1, Duration::from_secs(10)).unwrap(), 1);
            for frame in 0..3u64 {
                let header = HypothesesHeader {
                    header: Header::new(frame, 1),
                    sample_count: 1,
                    step_count: 1,
                    ..Default::default()
                };
                let mut meanwhile = || {
                    served.fetch_add(1, Ordering::SeqCst);
                };
                publisher.publish_serving(header, POSE_LEN, |p| p.fill(frame as f32), &mut meanwhile).unwrap();
            }
            publisher.end_of_stream(Duration::from_secs(10)).unwrap()
        }
    });
    let mut frames = Vec::new();
    let started = std::time::Instant::now();
    while frames.len() < 3 {
        subscriber.take_events().unwrap();
        // Read only after the sender, stuck on the full queue, has served.
        if served.load(Ordering::SeqCst) > 0 || sender.is_finished() {
            while let Some(message) = subscriber.receive().unwrap() {
                frames.push(message.header().header.frame_id);
            }
        }
        assert!(started.elapsed() < Duration::from_secs(20), "the blocked publisher never served; got {frames:?}");
        std::thread::sleep(Duration::from_millis(1));
    }
    subscriber.acknowledge_end().unwrap();
    sender.join().unwrap();
    assert_eq!(frames, vec![0, 1, 2]);
    assert!(served.load(Ordering::SeqCst) > 0);
}

/// A reader that subscribed before the publisher existed and is busy for a
/// while (a selector building its distance grids) answers READY only when
/// it next touches its port. The publisher must wait for it however long
/// that takes: sending earlier goes into a half-made connection, where
/// iceoryx2 keeps the first queue-full and silently drops the rest (seen:
/// 8 of 20 estimates).
#[test]
fn a_publisher_waits_for_a_reader_that_is_slow_to_answer() {
    let name = edge_service_name(&format!("test-slow-reader-{}", std::process::id()), "poses").unwrap();
    let options = EdgeOptions { queue: 4, overflow: Overflow::Block, max_payload_len: 64 };
    let node = create_node("slow-receiver").unwrap();
    let subscriber = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    // Warned about every 50 ms, never given up on.
    let sender = spawn_sender(&name, options, 20, |publisher| {
        publisher.wait_for_all_receivers_serving(1, Duration::from_millis(50), &mut || {}).unwrap()
    });
    // Busy for many warning periods before touching the port.
    std::thread::sleep(Duration::from_millis(600));
    let frames = receive_until_end(&subscriber, Duration::from_millis(5));
    assert_eq!(sender.join().unwrap(), 1);
    assert_eq!(frames, (0..20).collect::<Vec<_>>());
}

/// READY counts receivers, not notifications: a receiver may say READY
/// more than once (at creation, and again on seeing the publisher appear),
/// and one that said it may be gone. Counting notifications let a publisher
/// waiting for two readers start before the second existed, and its first
/// messages never reached it (seen: 15 of 424 observations lost by the
/// inference stage, which subscribes after loading its model).
#[test]
fn ready_counts_receivers_not_notifications() {
    let name = edge_service_name(&format!("test-ready-count-{}", std::process::id()), "poses").unwrap();
    let options = EdgeOptions { queue: 4, overflow: Overflow::Block, max_payload_len: 64 };
    let node = create_node("ready-count").unwrap();
    let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    let _first = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    // Two READY notifications, one receiver left.
    drop(EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap());
    assert_eq!(publisher.wait_for_receivers(2, Duration::from_millis(300)).unwrap(), 1);
    // READY said before an earlier wait still counts in a later one.
    let _second = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    assert_eq!(publisher.wait_for_receivers(2, Duration::from_secs(10)).unwrap(), 2);
}

/// A reader killed and replaced (by the supervisor) misses nothing sent
/// while it was gone: on a `block` edge the send waits for the replacement
/// to say READY. Before, such sends reached no one and nothing counted them
/// (seen: a tracking graph lost 7 observations' handles while its sampler
/// was replaced, on top of what the dead sampler's queue held).
#[test]
fn a_send_waits_for_a_replaced_reader() {
    let name = edge_service_name(&format!("test-replaced-{}", std::process::id()), "poses").unwrap();
    let options = EdgeOptions { queue: 4, overflow: Overflow::Block, max_payload_len: 64 };
    let node = create_node("replaced-receiver").unwrap();
    let first = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    let (reader_gone, gone) = std::sync::mpsc::channel::<()>();
    let sender = std::thread::spawn({
        let name = name.clone();
        move || {
            let node = create_node("replaced-sender").unwrap();
            let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &options).unwrap();
            assert_eq!(publisher.wait_for_receivers(1, Duration::from_secs(10)).unwrap(), 1);
            let mut receivers = Vec::new();
            for frame in 0..6u64 {
                if frame == 1 {
                    gone.recv().unwrap();
                }
                let header = HypothesesHeader {
                    header: Header::new(frame, 1),
                    sample_count: 1,
                    step_count: 1,
                    ..Default::default()
                };
                let sent = publisher.publish(header, POSE_LEN, |p| p.fill(frame as f32)).unwrap();
                receivers.push((sent, publisher.missed_a_reader(sent)));
            }
            publisher.end_of_stream(Duration::from_secs(10)).unwrap();
            receivers
        }
    });
    let started = std::time::Instant::now();
    let mut before = Vec::new();
    while before.is_empty() {
        first.take_events().unwrap();
        while let Some(message) = first.receive().unwrap() {
            before.push(message.header().header.frame_id);
        }
        assert!(started.elapsed() < Duration::from_secs(20), "frame 0 never arrived");
        std::thread::sleep(Duration::from_millis(1));
    }
    drop(first);
    reader_gone.send(()).unwrap();
    // The replacement takes a while to start, as a restarted stage does.
    std::thread::sleep(Duration::from_millis(300));
    let replacement = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    let mut after = Vec::new();
    while after.len() < 5 && started.elapsed() < Duration::from_secs(20) {
        replacement.take_events().unwrap();
        while let Some(message) = replacement.receive().unwrap() {
            after.push(message.header().header.frame_id);
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(before, vec![0]);
    assert_eq!(after, (1..6).collect::<Vec<_>>());
    replacement.acknowledge_end().unwrap();
    assert_eq!(sender.join().unwrap(), vec![(1, false); 6]);
}

/// On a `drop-oldest` edge a send does not wait for a missing reader, and
/// says that it missed one.
#[test]
fn a_drop_oldest_send_to_a_missing_reader_says_so() {
    let name = edge_service_name(&format!("test-missing-{}", std::process::id()), "poses").unwrap();
    let options = EdgeOptions { queue: 4, overflow: Overflow::DropOldest, max_payload_len: 64 };
    let node = create_node("missing-reader").unwrap();
    let publisher = Publisher::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    let reader = EdgeSubscriber::<HypothesesHeader>::create(&node, &name, &options).unwrap();
    assert_eq!(publisher.wait_for_receivers(1, Duration::from_secs(10)).unwrap(), 1);
    let header = HypothesesHeader { header: Header::new(0, 1), sample_count: 1, step_count: 1, ..Default::default() };
    let sent = publisher.publish(header, POSE_LEN, |p| p.fill(0.0)).unwrap();
    assert_eq!((sent, publisher.missed_a_reader(sent)), (1, false));
    drop(reader);
    let sent = publisher.publish(header, POSE_LEN, |p| p.fill(0.0)).unwrap();
    assert_eq!((sent, publisher.missed_a_reader(sent)), (0, true));
}
