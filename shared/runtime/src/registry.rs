//! Which stages exist and how each is built. A service crate registers each
//! of its stages once (executable name, kind, and the `make` function that
//! builds it from its wiring); the stage's binary runs the registration as
//! a process, and the launcher runs the same registration as a thread of a
//! [`LocalGraph`]. There is no second way to build a stage.

use std::collections::BTreeMap;
use std::process::ExitCode;

use poseflow_contracts::StampSlot;
use poseflow_graph::{EdgeWiring, StageWiring};

use crate::error::{BuildError, RuntimeError};
use crate::local::LocalGraph;
use crate::process::{run_joined, run_server, run_sink, run_source, run_transform, run_transform_or_joined};
use crate::stage::{Joined, Server, Sink, Source, Transform};

/// Which of the runtime's loops drives a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageKind {
    /// No input, one output ([`Source`]).
    Source,
    /// One input, one output ([`Transform`]).
    Transform,
    /// One input, no output ([`Sink`]).
    Sink,
    /// A transform that also answers one request-response edge ([`Server`]).
    Server,
    /// A transform that also reads side inputs ([`Joined`]).
    Joined,
    /// A [`Joined`] stage whose side inputs are optional: it runs as a plain
    /// transform where the graph gives it none.
    TransformOrJoined,
}

impl StageKind {
    pub fn label(self) -> &'static str {
        match self {
            StageKind::Source => "source",
            StageKind::Transform => "transform",
            StageKind::Sink => "sink",
            StageKind::Server => "server",
            StageKind::Joined => "joined",
            StageKind::TransformOrJoined => "transform (joined with side inputs)",
        }
    }
}

type AddLocal = Box<dyn Fn(&mut LocalGraph, &StageWiring) -> Result<(), RuntimeError> + Send + Sync>;
type RunProcess = Box<dyn Fn() -> ExitCode + Send + Sync>;

/// One stage a service crate offers.
pub struct Registration {
    exe: &'static str,
    kind: StageKind,
    /// The timestamp slot of the stage type, unless the graph chooses one.
    stamp: Option<StampSlot>,
    run_process: RunProcess,
    /// `None` for kinds the in-process graph cannot run yet.
    add_local: Option<AddLocal>,
}

impl std::fmt::Debug for Registration {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Registration").field("exe", &self.exe).field("kind", &self.kind).finish()
    }
}

/// The one edge a stage of this kind has in `field`.
fn single<'a>(wiring: &'a StageWiring, field: &'static str, edges: &'a [EdgeWiring]) -> Result<&'a str, RuntimeError> {
    match edges {
        [edge] => Ok(&edge.edge),
        _ => Err(RuntimeError::Shape {
            stage: wiring.stage.clone(),
            expected: match field {
                "inputs" => "exactly one input edge",
                _ => "exactly one output edge",
            },
            found: format!("{} edge(s) in `{field}`", edges.len()),
        }),
    }
}

/// `make` bound to a copy of `wiring`, to run on the stage's own thread.
fn deferred<T: 'static, E: Into<BuildError> + 'static>(
    wiring: &StageWiring,
    make: fn(&StageWiring) -> Result<T, E>,
) -> impl FnOnce() -> Result<T, BuildError> + Send + 'static {
    let wiring = wiring.clone();
    move || make(&wiring).map_err(Into::into)
}

/// The one edge of a kind a stage must have exactly one of.
fn exactly_one<'a>(
    wiring: &'a StageWiring,
    edges: &'a [EdgeWiring],
    expected: &'static str,
) -> Result<&'a EdgeWiring, RuntimeError> {
    match edges {
        [edge] => Ok(edge),
        _ => Err(RuntimeError::Shape {
            stage: wiring.stage.clone(),
            expected,
            found: format!("{} such edge(s)", edges.len()),
        }),
    }
}

/// Adds a transform, joined with its side input if the graph gives one.
fn add_transform_or_joined<J, E>(
    local: &mut LocalGraph,
    wiring: &StageWiring,
    make: fn(&StageWiring) -> Result<J, E>,
    side_required: bool,
) -> Result<(), RuntimeError>
where
    J: Transform + Joined + 'static,
    J::In: Send + 'static,
    J::Out: Send + 'static,
    J::Side: Send + 'static,
    E: Into<BuildError> + 'static,
{
    let input = single(wiring, "inputs", &wiring.inputs)?;
    let output = single(wiring, "outputs", &wiring.outputs)?;
    if wiring.side_inputs.is_empty() && !side_required {
        return Ok(local.add_transform(&wiring.stage, deferred(wiring, make), input, output)?);
    }
    let side = exactly_one(wiring, &wiring.side_inputs, "exactly one side input")?;
    Ok(local.add_joined(&wiring.stage, deferred(wiring, make), input, &side.edge, output)?)
}

impl Registration {
    pub fn source<S, E>(exe: &'static str, make: fn(&StageWiring) -> Result<S, E>) -> Self
    where
        S: Source + 'static,
        S::Out: Send + 'static,
        E: Into<BuildError> + 'static,
    {
        Self {
            exe,
            kind: StageKind::Source,
            stamp: S::SLOT,
            run_process: Box::new(move || run_source(make)),
            add_local: Some(Box::new(move |local, wiring| {
                let output = single(wiring, "outputs", &wiring.outputs)?;
                let rate_hz = wiring.params.get("rate_hz").and_then(|v| v.as_f64());
                Ok(local.add_source(&wiring.stage, deferred(wiring, make), output, rate_hz)?)
            })),
        }
    }

    pub fn transform<T, E>(exe: &'static str, make: fn(&StageWiring) -> Result<T, E>) -> Self
    where
        T: Transform + 'static,
        T::In: Send + 'static,
        T::Out: Send + 'static,
        E: Into<BuildError> + 'static,
    {
        Self {
            exe,
            kind: StageKind::Transform,
            stamp: T::SLOT,
            run_process: Box::new(move || run_transform(make)),
            add_local: Some(Box::new(move |local, wiring| {
                let input = single(wiring, "inputs", &wiring.inputs)?;
                let output = single(wiring, "outputs", &wiring.outputs)?;
                Ok(local.add_transform(&wiring.stage, deferred(wiring, make), input, output)?)
            })),
        }
    }

    pub fn sink<K, E>(exe: &'static str, make: fn(&StageWiring) -> Result<K, E>) -> Self
    where
        K: Sink + 'static,
        K::In: Send + 'static,
        E: Into<BuildError> + 'static,
    {
        Self {
            exe,
            kind: StageKind::Sink,
            stamp: None,
            run_process: Box::new(move || run_sink(make)),
            add_local: Some(Box::new(move |local, wiring| {
                let input = single(wiring, "inputs", &wiring.inputs)?;
                Ok(local.add_sink(&wiring.stage, deferred(wiring, make), input)?)
            })),
        }
    }

    pub fn server<S, E>(exe: &'static str, make: fn(&StageWiring) -> Result<S, E>) -> Self
    where
        S: Server + 'static,
        S::In: Send + 'static,
        S::Out: Send + 'static,
        S::Request: Send + 'static,
        S::Response: Send + 'static,
        E: Into<BuildError> + 'static,
    {
        Self {
            exe,
            kind: StageKind::Server,
            stamp: S::SLOT,
            run_process: Box::new(move || run_server(make)),
            add_local: Some(Box::new(move |local, wiring| {
                let input = single(wiring, "inputs", &wiring.inputs)?;
                let output = single(wiring, "outputs", &wiring.outputs)?;
                let served = exactly_one(wiring, &wiring.serves, "one request-response edge it serves")?;
                Ok(local.add_server(&wiring.stage, deferred(wiring, make), input, &served.service, output)?)
            })),
        }
    }

    pub fn joined<J, E>(exe: &'static str, make: fn(&StageWiring) -> Result<J, E>) -> Self
    where
        J: Transform + Joined + 'static,
        J::In: Send + 'static,
        J::Out: Send + 'static,
        J::Side: Send + 'static,
        E: Into<BuildError> + 'static,
    {
        Self::with_side_input(exe, make, true)
    }

    pub fn transform_or_joined<J, E>(exe: &'static str, make: fn(&StageWiring) -> Result<J, E>) -> Self
    where
        J: Transform + Joined + 'static,
        J::In: Send + 'static,
        J::Out: Send + 'static,
        J::Side: Send + 'static,
        E: Into<BuildError> + 'static,
    {
        Self::with_side_input(exe, make, false)
    }

    fn with_side_input<J, E>(exe: &'static str, make: fn(&StageWiring) -> Result<J, E>, required: bool) -> Self
    where
        J: Transform + Joined + 'static,
        J::In: Send + 'static,
        J::Out: Send + 'static,
        J::Side: Send + 'static,
        E: Into<BuildError> + 'static,
    {
        Self {
            exe,
            kind: if required { StageKind::Joined } else { StageKind::TransformOrJoined },
            stamp: J::SLOT,
            run_process: if required {
                Box::new(move || run_joined(make))
            } else {
                Box::new(move || run_transform_or_joined(make))
            },
            add_local: Some(Box::new(move |local, wiring| add_transform_or_joined(local, wiring, make, required))),
        }
    }

    /// A source whose message type is the output edge's (a replay, a
    /// bridge): `pick` returns the registration typed for that message.
    pub fn source_of_any_message(exe: &'static str, pick: fn(&str) -> Option<Registration>) -> Self {
        let typed = move |wiring: &StageWiring| {
            let message = wiring.outputs.first().map(|o| o.message.as_str()).unwrap_or_default();
            pick(message).ok_or_else(|| RuntimeError::Shape {
                stage: wiring.stage.clone(),
                expected: "one output edge with a contract message type",
                found: format!("{message:?}"),
            })
        };
        Self {
            exe,
            kind: StageKind::Source,
            // A replay keeps the recorded stamps: no slot of its own.
            stamp: None,
            run_process: Box::new(move || match StageWiring::from_env() {
                Ok(wiring) => match typed(&wiring) {
                    Ok(registration) => registration.run_process(),
                    Err(err) => crate::process::fail(err),
                },
                Err(err) => crate::process::fail(RuntimeError::Wiring(err)),
            }),
            add_local: Some(Box::new(move |local, wiring| typed(wiring)?.add_to(local, wiring))),
        }
    }

    /// The executable name graph files give in `exe`.
    pub fn exe(&self) -> &'static str {
        self.exe
    }

    pub fn kind(&self) -> StageKind {
        self.kind
    }

    /// The slot the stage writes where its graph entry has no `stamp`.
    pub fn default_stamp(&self) -> Option<StampSlot> {
        self.stamp
    }

    /// Whether [`Self::add_to`] can run this stage in-process.
    pub fn runs_in_process(&self) -> bool {
        self.add_local.is_some()
    }

    /// Runs the stage as this process: the whole `main` of a stage binary.
    pub fn run_process(&self) -> ExitCode {
        (self.run_process)()
    }

    /// Builds the stage from `wiring` and adds it to `local` as a thread.
    pub fn add_to(&self, local: &mut LocalGraph, wiring: &StageWiring) -> Result<(), RuntimeError> {
        if wiring.stamp.is_some() {
            local.stamp_as(&wiring.stage, wiring.stamp_slot(None));
        }
        match &self.add_local {
            Some(add) => add(local, wiring),
            None => Err(RuntimeError::NotInProcess { stage: wiring.stage.clone(), kind: self.kind.label() }),
        }
    }
}

/// Every registered stage, by executable name.
#[derive(Debug, Default)]
pub struct Registry {
    by_exe: BTreeMap<&'static str, Registration>,
}

impl Registry {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds registrations; a later one with the same name replaces the
    /// earlier (so a user's registry can override a built-in stage).
    pub fn with(mut self, registrations: impl IntoIterator<Item = Registration>) -> Self {
        for registration in registrations {
            self.by_exe.insert(registration.exe, registration);
        }
        self
    }

    pub fn get(&self, exe: &str) -> Option<&Registration> {
        self.by_exe.get(exe)
    }

    pub fn iter(&self) -> impl Iterator<Item = &Registration> {
        self.by_exe.values()
    }

    /// The names of the stages that can run in-process.
    pub fn in_process_names(&self) -> Vec<&'static str> {
        self.by_exe.values().filter(|r| r.runs_in_process()).map(|r| r.exe).collect()
    }
}

/// The `main` of a stage binary: runs the registration named `exe` from a
/// service crate's list as this process.
pub fn run_registered(registrations: Vec<Registration>, exe: &str) -> ExitCode {
    match registrations.into_iter().find(|r| r.exe == exe) {
        Some(registration) => registration.run_process(),
        None => {
            crate::init_logging();
            tracing::error!(exe, "no stage of this name is registered by the binary's crate");
            ExitCode::FAILURE
        }
    }
}
