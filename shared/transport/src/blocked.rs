//! What a publisher blocked on a full receive queue does while it waits.
//!
//! A stage that also answers requests (the inference stage) must keep
//! answering while its output is backed up: its reader may be the very
//! client waiting for an answer, and would otherwise never drain the queue
//! the publisher waits on. iceoryx2 calls a publisher's backpressure handler
//! on every retry of a blocked send; ours runs the closure that
//! [`while_blocked`] installed on this thread for the duration of one send.

use std::cell::Cell;
use std::ptr::NonNull;
use std::time::Duration;

use iceoryx2::port::{BackpressureAction, BackpressureInfo};

type Hook = NonNull<dyn FnMut() + 'static>;

thread_local! {
    static HOOK: Cell<Option<Hook>> = const { Cell::new(None) };
}

/// Removes the hook when the send returns, even by unwinding.
struct Installed(Option<Hook>);

impl Drop for Installed {
    fn drop(&mut self) {
        HOOK.with(|hook| hook.set(self.0));
    }
}

/// Runs `send` with `meanwhile` called between the retries of any blocked
/// publish on this thread.
pub(crate) fn while_blocked<T>(meanwhile: &mut dyn FnMut(), send: impl FnOnce() -> T) -> T {
    let pointer = NonNull::from(meanwhile);
    // SAFETY: only the lifetime is erased. The pointer is reachable only
    // through this thread's HOOK, which `Installed` restores before this
    // function returns, so it is never called after `meanwhile`'s borrow ends.
    let pointer: Hook = unsafe { std::mem::transmute::<NonNull<dyn FnMut() + '_>, Hook>(pointer) };
    let _installed = Installed(HOOK.with(|hook| hook.replace(Some(pointer))));
    send()
}

/// Retries of a blocked send that only yield the processor, for a slot
/// freed within microseconds.
const YIELDING_RETRIES: u64 = 32;

/// The longest pause between later retries: how late a freed slot (and, in
/// a stage that serves requests meanwhile, a request) is noticed at most.
const LONGEST_PAUSE: Duration = Duration::from_micros(250);

/// How long to pause before retry `retries` of a send blocked for
/// `elapsed`. iceoryx2 itself only yields between its first 10,000 retries:
/// in a saturated graph on two cores, the writers blocked on full queues
/// spun away a tenth of the CPU time the networks needed. Pausing a quarter
/// of the time blocked so far keeps the extra wait under a quarter of it.
fn pause(retries: u64, elapsed: Duration) -> Option<Duration> {
    (retries >= YIELDING_RETRIES).then(|| (elapsed / 4).min(LONGEST_PAUSE))
}

/// The backpressure handler of blocking publishers: runs the installed
/// closure, if any, pauses once the send has been blocked a while, and
/// retries.
pub(crate) fn on_backpressure(info: &BackpressureInfo) -> BackpressureAction {
    HOOK.with(|hook| {
        // Taken while it runs, so a publish inside it cannot re-enter it.
        if let Some(mut meanwhile) = hook.take() {
            // SAFETY: installed by `while_blocked` on this thread, whose
            // borrow of the closure is live while its send is (we are inside
            // that send); nothing else holds the closure meanwhile.
            unsafe { meanwhile.as_mut()() };
            hook.set(Some(meanwhile));
        }
    });
    if let Some(pause) = pause(info.retries, info.elapsed_time) {
        std::thread::sleep(pause);
    }
    BackpressureAction::Retry
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info() -> BackpressureInfo {
        BackpressureInfo {
            service_id: 0,
            sender_port_id: 0,
            receiver_port_id: 0,
            retries: 0,
            elapsed_time: Default::default(),
        }
    }

    #[test]
    fn the_hook_runs_only_inside_its_send_and_never_reenters() {
        let mut calls = 0;
        assert_eq!(on_backpressure(&info()), BackpressureAction::Retry);
        while_blocked(&mut || calls += 1, || {
            on_backpressure(&info());
            on_backpressure(&info());
        });
        assert_eq!(calls, 2);
        // Gone after the send.
        on_backpressure(&info());
        assert_eq!(calls, 2);
        // Nested: the inner hook replaces the outer one, then hands it back.
        let (mut outer, mut inner) = (0, 0);
        while_blocked(&mut || outer += 1, || {
            while_blocked(&mut || inner += 1, || on_backpressure(&info()));
            on_backpressure(&info());
        });
        assert_eq!((outer, inner), (1, 1));
    }

    #[test]
    fn a_long_blocked_send_pauses_between_retries_a_bounded_share_of_its_wait() {
        assert_eq!(pause(0, Duration::from_millis(50)), None);
        assert_eq!(pause(YIELDING_RETRIES - 1, Duration::from_millis(50)), None);
        assert_eq!(pause(YIELDING_RETRIES, Duration::from_micros(400)), Some(Duration::from_micros(100)));
        assert_eq!(pause(u64::MAX, Duration::from_secs(3)), Some(LONGEST_PAUSE));
        let pauses: Vec<Duration> =
            (0..2000u64).filter_map(|us| pause(YIELDING_RETRIES, Duration::from_micros(us))).collect();
        assert!(pauses.windows(2).all(|w| w[0] <= w[1]), "pauses never shrink as the wait grows");
    }

    #[test]
    fn a_publish_inside_the_hook_does_not_call_it_again() {
        let depth = std::cell::Cell::new(0);
        let mut meanwhile = || {
            depth.set(depth.get() + 1);
            on_backpressure(&info());
        };
        while_blocked(&mut meanwhile, || on_backpressure(&info()));
        assert_eq!(depth.get(), 1);
    }
}
