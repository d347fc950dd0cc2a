//! Preemption: clusters end jobs with a signal (Slurm sends SIGTERM on preemption or `scancel`,
//! and the signal `--signal` asks for ahead of the time limit), then SIGKILL a little later.
//! While a [`PreemptWatch`] is alive, the first of its signals only raises a flag: the training
//! loop finishes its optimizer step, the ranks agree (see [`super::consensus`]), a complete
//! checkpoint is written and the process exits with [`EXIT_PREEMPTED`]. A second signal, or the
//! grace deadline after the first, ends the process at once (`_exit` from the signal handler or
//! the watch thread) with [`forced_exit_status`]: no checkpoint is left half marked, because a
//! checkpoint only counts once its `state.json` is in (see `checkpoint`).
//!
//! The first signal is only deferred while something checkpointable runs (a [`Checkpointable`]
//! section: the training loop, `trainer nvs`'s renders and samples). Outside one (start-up:
//! checking checkpoints on `--resume`, loading models, building pairs) there is nothing to save,
//! and a watched signal ends the process at once with [`forced_exit_status`].
//!
//! Handlers are registered once per process and signal and stay registered; when no watch is
//! alive they act as the signal's default action (terminate), so a process that is not training
//! behaves as if none were installed.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use signal_hook::consts::signal;

use crate::error::{Error, Result};

/// Exit status of a run that stopped for a preemption signal after writing a complete checkpoint
/// of its last step (BSD `sysexits.h` EX_TEMPFAIL: a temporary failure, try again; the job
/// script requeues on it and the next run `--resume`s).
pub const EXIT_PREEMPTED: i32 = 75;
/// Exit status of a run stopped because a checkpoint could not be written (disk full, quota, I/O
/// error): the earlier checkpoints are untouched (EX_IOERR). Not retried by the job script: the
/// disk needs attention first.
pub const EXIT_CHECKPOINT_FAILED: i32 = 74;

/// Exit status of a run ended at once by a second signal or the grace deadline: 128 + the
/// signal's number, what a shell reports for a process the signal killed. No checkpoint of the
/// current step; `--resume` continues from the last complete one.
pub fn forced_exit_status(signal: i32) -> i32 {
    128 + signal
}

/// The signals `[loop] preempt_signals` may name.
pub const SIGNALS: [(&str, i32); 5] = [
    ("SIGTERM", signal::SIGTERM),
    ("SIGUSR1", signal::SIGUSR1),
    ("SIGUSR2", signal::SIGUSR2),
    ("SIGINT", signal::SIGINT),
    ("SIGHUP", signal::SIGHUP),
];

/// The number of a signal name of [`SIGNALS`].
pub fn signal_number(name: &str) -> Option<i32> {
    SIGNALS.iter().find(|(n, _)| *n == name).map(|&(_, number)| number)
}

/// The name of a signal number of [`SIGNALS`] (`signal N` for others).
pub fn signal_name(number: i32) -> String {
    SIGNALS.iter().find(|(_, n)| *n == number).map_or_else(|| format!("signal {number}"), |(name, _)| name.to_string())
}

/// How often the watch thread looks at the flags (latency of its message and of the deadline).
const POLL: Duration = Duration::from_millis(20);

/// Process-wide handler state, shared by every watch.
struct Handlers {
    /// Per registered signal: true while no watch listens to it (the handler then acts as the
    /// default action).
    idle: Mutex<BTreeMap<i32, Arc<AtomicBool>>>,
    /// Set by the first signal a watch listens to; a further one then exits at once.
    received: Arc<AtomicBool>,
    /// The first signal's number.
    which: Arc<AtomicUsize>,
    /// Live watches (the flags are reset when the first one starts).
    watches: Mutex<usize>,
    /// True while no [`Checkpointable`] section runs: a signal then ends the process at once.
    at_once: Arc<AtomicBool>,
    /// Live [`Checkpointable`] sections.
    checkpointable: Mutex<usize>,
}

fn handlers() -> &'static Handlers {
    static HANDLERS: OnceLock<Handlers> = OnceLock::new();
    HANDLERS.get_or_init(|| Handlers {
        idle: Mutex::new(BTreeMap::new()),
        received: Arc::new(AtomicBool::new(false)),
        which: Arc::new(AtomicUsize::new(0)),
        watches: Mutex::new(0),
        at_once: Arc::new(AtomicBool::new(true)),
        checkpointable: Mutex::new(0),
    })
}

/// A section of work that a preemption signal may wait for (see the module docs): while one is
/// alive, the first watched signal only raises the flag [`PreemptWatch::received`] reads;
/// outside every section it ends the process at once.
#[derive(Debug)]
pub struct Checkpointable(());

impl Checkpointable {
    /// Enters a checkpointable section until the value is dropped.
    pub fn enter() -> Self {
        let h = handlers();
        let mut sections = h.checkpointable.lock().expect("no panic while held");
        *sections += 1;
        h.at_once.store(false, Ordering::SeqCst);
        Self(())
    }
}

impl Drop for Checkpointable {
    fn drop(&mut self) {
        let h = handlers();
        let mut sections = h.checkpointable.lock().expect("no panic while held");
        *sections -= 1;
        if *sections == 0 {
            h.at_once.store(true, Ordering::SeqCst);
        }
    }
}

/// Watches for preemption signals while a run trains (see the module docs).
pub struct PreemptWatch {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl PreemptWatch {
    /// Starts watching `signals` (numbers from [`signal_number`]); with `grace`, the process
    /// exits that long after the first signal if it has not ended by then.
    pub fn install(signals: &[i32], grace: Option<Duration>) -> Result<Self> {
        let h = handlers();
        let mut idle = h.idle.lock().expect("no panic while held");
        // Every handler is registered (once per process) before any is armed.
        for &sig in signals {
            if let std::collections::btree_map::Entry::Vacant(entry) = idle.entry(sig) {
                let flag = Arc::new(AtomicBool::new(true));
                register(sig, &flag, h).map_err(|e| Error::InvalidArgument {
                    name: "loop.preempt_signals".to_string(),
                    reason: format!("cannot handle {}: {e}", signal_name(sig)),
                })?;
                entry.insert(flag);
            }
        }
        {
            let mut watches = h.watches.lock().expect("no panic while held");
            if *watches == 0 {
                h.received.store(false, Ordering::SeqCst);
                h.which.store(0, Ordering::SeqCst);
            }
            *watches += 1;
        }
        for sig in signals {
            idle[sig].store(false, Ordering::SeqCst);
        }
        drop(idle);
        // Armed from here on: should the thread not start, dropping `this` disarms again.
        let mut this = Self { stop: Arc::new(AtomicBool::new(false)), thread: None };
        let (stop, received, which) = (this.stop.clone(), h.received.clone(), h.which.clone());
        let thread = std::thread::Builder::new()
            .name("preempt-watch".to_string())
            .spawn(move || watch(&stop, &received, &which, grace))
            .map_err(|error| Error::Io { path: "<preemption watch thread>".into(), error })?;
        this.thread = Some(thread);
        Ok(this)
    }

    /// The first signal received since the watch started, if any (this process only: the
    /// training loop agrees on it with the other ranks).
    pub fn received(&self) -> Option<i32> {
        let h = handlers();
        h.received.load(Ordering::SeqCst).then(|| h.which.load(Ordering::SeqCst) as i32)
    }

    /// After a preempted run's checkpoint: keeps the handlers armed until the process exits, the
    /// signal already acted on forgotten, so that one more signal while the process exits (srun
    /// sends SIGTERM to the other tasks as soon as one has exited) cannot turn its exit status
    /// into 128 + N. A further one still ends it at once.
    pub fn hold_until_exit(mut self) {
        // The exit is the end of a checkpointable section that never closes.
        std::mem::forget(Checkpointable::enter());
        self.stop.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        handlers().received.store(false, Ordering::SeqCst);
        // Never disarmed: the process is about to exit with its status.
        std::mem::forget(self);
    }
}

impl Drop for PreemptWatch {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        let h = handlers();
        let mut watches = h.watches.lock().expect("no panic while held");
        *watches -= 1;
        if *watches == 0 {
            // No watch left: every handler acts as its signal's default action again.
            for flag in h.idle.lock().expect("no panic while held").values() {
                flag.store(true, Ordering::SeqCst);
            }
        }
    }
}

/// The handler's actions for `sig`, in the order they run: the default action while idle; exit
/// at once outside a checkpointable section or on a second signal; else raise the flag and
/// record which signal it was.
fn register(sig: i32, idle: &Arc<AtomicBool>, h: &Handlers) -> std::io::Result<()> {
    signal_hook::flag::register_conditional_default(sig, idle.clone())?;
    signal_hook::flag::register_conditional_shutdown(sig, forced_exit_status(sig), h.at_once.clone())?;
    signal_hook::flag::register_conditional_shutdown(sig, forced_exit_status(sig), h.received.clone())?;
    signal_hook::flag::register(sig, h.received.clone())?;
    signal_hook::flag::register_usize(sig, h.which.clone(), sig as usize)?;
    Ok(())
}

/// The watch thread: says when the first signal arrived, and enforces the grace deadline.
fn watch(stop: &AtomicBool, received: &AtomicBool, which: &AtomicUsize, grace: Option<Duration>) {
    let mut since: Option<Instant> = None;
    while !stop.load(Ordering::SeqCst) {
        if received.load(Ordering::SeqCst) {
            let sig = which.load(Ordering::SeqCst) as i32;
            let first = *since.get_or_insert_with(|| {
                let deadline = grace.map_or(String::new(), |g| format!(", or {:.0} s from now", g.as_secs_f64()));
                eprintln!(
                    "{}: finishing the current step, then a checkpoint and exit status {EXIT_PREEMPTED} \
                     (a second signal{deadline} stops at once without a checkpoint)",
                    signal_name(sig)
                );
                Instant::now()
            });
            if grace.is_some_and(|g| first.elapsed() >= g) {
                let status = forced_exit_status(sig);
                eprintln!(
                    "{}: the grace period of {:.0} s is over: stopping now, exit status {status}, no checkpoint \
                     of this step (--resume continues from the last complete one)",
                    signal_name(sig),
                    grace.unwrap_or_default().as_secs_f64()
                );
                signal_hook::low_level::exit(status);
            }
        }
        std::thread::sleep(POLL);
    }
}
