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

/// The backpressure handler of blocking publishers: runs the installed
/// closure, if any, and retries.
pub(crate) fn on_backpressure(_info: &BackpressureInfo) -> BackpressureAction {
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
