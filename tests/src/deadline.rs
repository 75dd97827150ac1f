//! Every process a test runs finishes within a deadline: a hung graph fails
//! its test with the graph's own log instead of using up the CI run's time
//! budget in silence.

use std::io::Read;
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How long one `poseflow` run of a test may take (the longest, the
/// pipeline benchmark in an unoptimised build, takes about a minute here).
pub const RUN_DEADLINE: Duration = Duration::from_secs(300);

/// How long a process has to stop after SIGINT before it is killed.
const STOP_GRACE: Duration = Duration::from_secs(15);

/// [`Command::output`] within a deadline.
pub trait OutputWithin {
    /// Runs to the end with stdout and stderr captured; past `limit` the
    /// process is interrupted (then killed) and the test fails with its
    /// stderr.
    fn output_within(&mut self, limit: Duration) -> Output;
}

impl OutputWithin for Command {
    fn output_within(&mut self, limit: Duration) -> Output {
        let child = self.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
        wait_within(child, limit)
    }
}

fn read_all(pipe: Option<impl Read + Send + 'static>) -> JoinHandle<Vec<u8>> {
    std::thread::spawn(move || {
        let mut bytes = Vec::new();
        if let Some(mut pipe) = pipe {
            let _ = pipe.read_to_end(&mut bytes);
        }
        bytes
    })
}

/// [`Child::wait_with_output`] within a deadline (as [`OutputWithin`]).
pub fn wait_within(mut child: Child, limit: Duration) -> Output {
    // Read both pipes all along: a child blocked on a full pipe never ends.
    let (stdout, stderr) = (read_all(child.stdout.take()), read_all(child.stderr.take()));
    let deadline = Instant::now() + limit;
    let mut interrupted: Option<Instant> = None;
    let status: ExitStatus = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        let now = Instant::now();
        match interrupted {
            None if now >= deadline => {
                // SAFETY: signalling a process this test started.
                unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
                interrupted = Some(now);
            }
            Some(at) if now >= at + STOP_GRACE => {
                let _ = child.kill();
            }
            _ => {}
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let output = Output { status, stdout: stdout.join().unwrap(), stderr: stderr.join().unwrap() };
    if interrupted.is_some() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        let tail: Vec<&str> = stderr.lines().rev().take(300).collect();
        let tail: Vec<&str> = tail.into_iter().rev().collect();
        panic!("still running after {limit:?}, so stopped ({status}); the last of its stderr:\n{}", tail.join("\n"));
    }
    output
}
