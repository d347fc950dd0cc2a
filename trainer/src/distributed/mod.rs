//! Multi-process training on PyTorch's own c10d engine: a TCPStore rendezvous and a Gloo (CPU) or
//! NCCL (CUDA) process group, reached through a small C++ shim (`trainer/csrc/`, the FFI in
//! [`ffi`]). The launcher decides who is who ([`Launch`]: torchrun, Slurm `srun` or variables set
//! by hand); [`ProcessGroup`] wraps the collectives the trainer needs with a timeout each, and turns
//! any failure into an error naming the collective and the ranks that did not take part in it.
//!
//! Failure reports: every rank records the sequence number of the collective it is entering under
//! `trainer/seq/RANK` in the store, and a heartbeat thread refreshes `trainer/alive/RANK` every
//! [`HEARTBEAT`]. When a collective fails or times out, the rank reads both for every other rank
//! and names those that stopped beating (dead or stalled) and those alive but not yet at the
//! collective. Gloo notices a dead peer at once (its sockets close); a stalled one within the
//! configured timeout.

pub mod comm_check;
mod data_parallel;
pub mod ffi;
mod launch;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use tch::{Device, Tensor};

pub use data_parallel::{FlatLayout, FlatState, GradientExchange, SHARD_PREFIX};
pub use ffi::{Backend, cuda_mem_get_info, cuda_memory_peaks, has_nccl};
pub use launch::{DEFAULT_MASTER_PORT, Launch, Launcher, first_host, launcher_world_size};

use crate::error::{Error, Result};

/// How often each rank refreshes its heartbeat key.
pub const HEARTBEAT: Duration = Duration::from_secs(1);
/// Heartbeat periods a failure report watches the other ranks' heartbeats for: one that does
/// not move in that time belongs to a dead or stopped rank.
const HEARTBEAT_WATCH: u32 = 3;
/// How long a failure report waits for another rank's keys (the store may be gone too).
const REPORT_WAIT_MS: i64 = 2000;

/// Joins the multi-process job the launcher started (torchrun, Slurm, `RANK`/`WORLD_SIZE`), if
/// any: one process per GPU, the CUDA device chosen by `LOCAL_RANK` when `device` is `cuda`
/// without an index. `None`: a single process on `device`.
pub fn join_job(device: Device, timeout_seconds: f64) -> Result<(Device, Option<ProcessGroup>)> {
    join(Launch::from_env()?, device, timeout_seconds)
}

/// [`join_job`] for a launch read already (None: a single process).
pub fn join(launch: Option<Launch>, device: Device, timeout_seconds: f64) -> Result<(Device, Option<ProcessGroup>)> {
    let Some(launch) = launch else { return Ok((device, None)) };
    let device = match device {
        Device::Cuda(index) => {
            let index = if index == 0 { launch.local_rank } else { index };
            let count = tch::Cuda::device_count() as usize;
            if index >= count {
                return Err(Error::Launcher {
                    variable: "LOCAL_RANK".to_string(),
                    reason: format!(
                        "rank {} (LOCAL_RANK {}) needs CUDA device {index}, but this machine has {count}",
                        launch.rank, launch.local_rank
                    ),
                });
            }
            Device::Cuda(index)
        }
        other => other,
    };
    let pg = ProcessGroup::init(&launch, device, Duration::from_secs_f64(timeout_seconds))?;
    Ok((device, Some(pg)))
}

/// One process's membership in the job: the store, the backend and the collectives.
pub struct ProcessGroup {
    group: Option<ffi::Group>,
    store: Option<Arc<ffi::Store>>,
    /// This process's rank.
    pub rank: usize,
    /// Number of ranks.
    pub world_size: usize,
    /// Rank on this machine.
    pub local_rank: usize,
    timeout_ms: i64,
    sequence: std::cell::Cell<u64>,
    failed: std::cell::Cell<bool>,
    heartbeat: Option<(Arc<AtomicBool>, std::thread::JoinHandle<()>)>,
    device: Device,
    backend: Backend,
}

/// A collective in flight, waited on with [`ProcessGroup::wait`].
pub struct Pending {
    work: ffi::Work,
    what: String,
    sequence: u64,
    started: Instant,
}

impl ProcessGroup {
    /// Joins the job `launch` describes, with collectives on `device` (Gloo for the CPU, NCCL for
    /// CUDA). Fails with a message naming the address when the store cannot be hosted (port in
    /// use) or reached (wrong MASTER_ADDR, rank 0 not started) within `timeout`.
    pub fn init(launch: &Launch, device: Device, timeout: Duration) -> Result<Self> {
        let timeout_ms = timeout.as_millis().min(i64::MAX as u128) as i64;
        let fail = |what: &str, reason: String| Error::Distributed {
            rank: launch.rank,
            world_size: launch.world_size,
            what: what.to_string(),
            reason,
        };
        let address = format!("{}:{}", launch.master_addr, launch.master_port);
        let hosts = launch.agent_store_prefix.is_none() && launch.rank == 0;
        let connect = |is_server: bool| {
            ffi::Store::new(
                &launch.master_addr,
                launch.master_port,
                is_server,
                launch.world_size,
                timeout_ms,
                launch.agent_store_prefix.as_deref(),
            )
        };
        let store = connect(hosts).map_err(|e| {
            if hosts {
                fail(
                    "rendezvous",
                    format!("could not host the store on {address} (is the port in use? set MASTER_PORT): {e}"),
                )
            } else {
                fail(
                    "rendezvous",
                    format!(
                        "could not reach the store at {address} within {:.0} s (is MASTER_ADDR right and rank 0 started?): {e}",
                        timeout.as_secs_f64()
                    ),
                )
            }
        })?;
        let store = Arc::new(store);
        let backend = if device.is_cuda() { Backend::Nccl } else { Backend::Gloo };
        // The heartbeat uses a connection of its own, so it never waits behind a collective's report.
        let beat_store =
            connect(false).map_err(|e| fail("rendezvous", format!("heartbeat connection to {address}: {e}")))?;
        let stop = Arc::new(AtomicBool::new(false));
        let rank = launch.rank;
        let thread = {
            let stop = stop.clone();
            std::thread::Builder::new()
                .name("c10d-heartbeat".to_string())
                .spawn(move || {
                    while !stop.load(Ordering::Relaxed) {
                        if beat_store
                            .set(&format!("trainer/alive/{rank}"), now_seconds().to_string().as_bytes())
                            .is_err()
                        {
                            return;
                        }
                        std::thread::sleep(HEARTBEAT);
                    }
                })
                .map_err(|e| fail("rendezvous", format!("cannot start the heartbeat thread: {e}")))?
        };
        let mut pg = Self {
            group: None,
            store: Some(store),
            rank,
            world_size: launch.world_size,
            local_rank: launch.local_rank,
            timeout_ms,
            sequence: std::cell::Cell::new(0),
            failed: std::cell::Cell::new(false),
            heartbeat: Some((stop, thread)),
            device,
            backend,
        };
        pg.mark(0)?;
        let group = ffi::Group::new(backend, pg.store(), launch.rank, launch.world_size, timeout_ms)
            .map_err(|e| pg.failure("process-group rendezvous", 0, Instant::now(), &e))?;
        pg.group = Some(group);
        Ok(pg)
    }

    fn store(&self) -> &ffi::Store {
        self.store.as_ref().expect("store lives until drop")
    }

    fn group(&self) -> &ffi::Group {
        self.group.as_ref().expect("group lives until drop")
    }

    /// The device collectives run on (tensors passed in must live there).
    pub fn device(&self) -> Device {
        self.device
    }

    /// The c10d backend: NCCL on CUDA devices, Gloo on the CPU.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// The timeout of every collective.
    pub fn timeout(&self) -> Duration {
        Duration::from_millis(self.timeout_ms as u64)
    }

    /// Records that this rank enters collective `sequence`.
    fn mark(&self, sequence: u64) -> Result<()> {
        self.store()
            .set(&format!("trainer/seq/{}", self.rank), sequence.to_string().as_bytes())
            .map_err(|e| self.failure("store", sequence, Instant::now(), &e))
    }

    fn next(&self) -> Result<u64> {
        let sequence = self.sequence.get() + 1;
        self.sequence.set(sequence);
        self.mark(sequence)?;
        Ok(sequence)
    }

    /// The error for a failed collective: the c10d message plus which ranks were missing.
    fn failure(&self, what: &str, sequence: u64, started: Instant, error: &ffi::FfiError) -> Error {
        self.failed.set(true);
        let read = |key: String| -> Option<u64> {
            let bytes = self.store.as_ref()?.get(&key, REPORT_WAIT_MS).ok()?;
            String::from_utf8(bytes).ok()?.parse().ok()
        };
        let others: Vec<usize> = (0..self.world_size).filter(|&r| r != self.rank).collect();
        let beats = |()| -> Vec<Option<u64>> { others.iter().map(|r| read(format!("trainer/alive/{r}"))).collect() };
        // A heartbeat that does not move over a few periods belongs to a dead or stopped rank.
        let before = beats(());
        std::thread::sleep(HEARTBEAT * HEARTBEAT_WATCH);
        let after = beats(());
        let now = now_seconds();
        let mut missing = Vec::new();
        for (i, &other) in others.iter().enumerate() {
            match (before[i], after[i]) {
                (_, None) => missing
                    .push(format!("rank {other}: no heartbeat in the store (never started, or the store is gone)")),
                (Some(a), Some(b)) if a == b => missing
                    .push(format!("rank {other}: no heartbeat for {} s (dead or stalled)", now.saturating_sub(b))),
                _ => match read(format!("trainer/seq/{other}")) {
                    Some(seen) if seen < sequence => {
                        missing.push(format!("rank {other}: alive but still before this collective (at #{seen})"))
                    }
                    _ => {}
                },
            }
        }
        let ranks = if missing.is_empty() { "every other rank reached it".to_string() } else { missing.join("; ") };
        Error::Distributed {
            rank: self.rank,
            world_size: self.world_size,
            what: format!("{what} (collective #{sequence})"),
            reason: format!("failed after {:.1} s: {error}; {ranks}", started.elapsed().as_secs_f64()),
        }
    }

    fn blocking(&self, what: &str, call: impl FnOnce(&ffi::Group, i64) -> ffi::FfiResult<()>) -> Result<()> {
        let sequence = self.next()?;
        let started = Instant::now();
        call(self.group(), self.timeout_ms).map_err(|e| self.failure(what, sequence, started, &e))
    }

    fn start(&self, what: &str, call: impl FnOnce(&ffi::Group, i64) -> ffi::FfiResult<ffi::Work>) -> Result<Pending> {
        let sequence = self.next()?;
        let started = Instant::now();
        let work = call(self.group(), self.timeout_ms).map_err(|e| self.failure(what, sequence, started, &e))?;
        Ok(Pending { work, what: what.to_string(), sequence, started })
    }

    /// Waits for a collective started by one of the `*_start` calls.
    pub fn wait(&self, pending: Pending) -> Result<()> {
        let Pending { work, what, sequence, started } = pending;
        work.wait(self.timeout_ms).map_err(|e| self.failure(&what, sequence, started, &e))
    }

    /// Orders what this thread runs on the device next after a collective started by one of the
    /// `*_start` calls, blocking the host only where it must: with NCCL the current CUDA stream
    /// waits on the collective's event and the host goes on (a failure or a stall then surfaces
    /// at the next [`Self::wait`], which blocks with the timeout); Gloo's CPU tensors need the
    /// host to wait, as [`Self::wait`] does.
    pub fn wait_on_stream(&self, pending: Pending) -> Result<()> {
        if self.backend == Backend::Gloo {
            return self.wait(pending);
        }
        let Pending { work, what, sequence, started } = pending;
        work.synchronize().map_err(|e| self.failure(&what, sequence, started, &e))
    }

    /// Starts an in-place sum of `tensor` over ranks.
    pub fn all_reduce_sum_start(&self, tensor: &Tensor, what: &str) -> Result<Pending> {
        self.start(&format!("all-reduce ({what})"), |g, t| g.allreduce_sum(tensor, t))
    }

    /// In-place sum of `tensor` over ranks.
    pub fn all_reduce_sum(&self, tensor: &Tensor, what: &str) -> Result<()> {
        let pending = self.all_reduce_sum_start(tensor, what)?;
        self.wait(pending)
    }

    /// In-place mean of `tensor` over ranks.
    pub fn all_reduce_mean(&self, tensor: &Tensor, what: &str) -> Result<()> {
        self.all_reduce_sum(tensor, what)?;
        let _ = tch::no_grad(|| tensor.shallow_clone().f_div_scalar_(self.world_size as f64))?;
        Ok(())
    }

    /// The sum over ranks of a scalar (reduced in f64 on the group's device).
    pub fn sum_f64(&self, value: f64, what: &str) -> Result<f64> {
        let tensor = Tensor::from_slice(&[value]).f_to_device(self.device)?;
        self.all_reduce_sum(&tensor, what)?;
        Ok(tensor.f_to_device(Device::Cpu)?.double_value(&[0]))
    }

    /// Broadcasts `tensor` from `root` in place.
    pub fn broadcast(&self, tensor: &Tensor, root: usize, what: &str) -> Result<()> {
        self.blocking(&format!("broadcast ({what})"), |g, t| g.broadcast(tensor, root, t))
    }

    /// Starts `output` = this rank's 1/N slice of the sum over ranks of `input`.
    pub fn reduce_scatter_sum_start(&self, output: &Tensor, input: &Tensor, what: &str) -> Result<Pending> {
        self.start(&format!("reduce-scatter ({what})"), |g, t| g.reduce_scatter_sum(output, input, t))
    }

    /// Starts `output` = every rank's `input` concatenated in rank order.
    pub fn all_gather_start(&self, output: &Tensor, input: &Tensor, what: &str) -> Result<Pending> {
        self.start(&format!("all-gather ({what})"), |g, t| g.all_gather(output, input, t))
    }

    /// Waits until every rank arrives.
    pub fn barrier(&self, what: &str) -> Result<()> {
        self.blocking(&format!("barrier ({what})"), |g, t| g.barrier(t))
    }

    /// Checks that every rank has the same value of each named item (config digest, shard set,
    /// checkpoint): fails on every rank, naming the item and the ranks that differ from rank 0.
    pub fn agree(&self, items: &[(&str, String)]) -> Result<()> {
        let sequence = self.next()?;
        let text = serde_json::to_string(items).expect("strings serialise");
        let key = |rank: usize| format!("trainer/agree/{sequence}/{rank}");
        let store = self.store();
        let started = Instant::now();
        store.set(&key(self.rank), text.as_bytes()).map_err(|e| self.failure("agreement", sequence, started, &e))?;
        let mut differences = Vec::new();
        for other in 0..self.world_size {
            let bytes = store
                .get(&key(other), self.timeout_ms)
                .map_err(|e| self.failure("agreement", sequence, started, &e))?;
            let theirs: Vec<(String, String)> = serde_json::from_slice(&bytes).unwrap_or_default();
            for ((name, mine), (_, value)) in items.iter().zip(&theirs) {
                if mine != value {
                    differences.push(format!("{name}: rank {} has {mine}, rank {other} has {value}", self.rank));
                }
            }
        }
        // Everyone reads before anyone moves on, so the keys are never read late.
        self.barrier("agreement")?;
        if differences.is_empty() {
            Ok(())
        } else {
            Err(Error::Distributed {
                rank: self.rank,
                world_size: self.world_size,
                what: "start-up check".to_string(),
                reason: format!("ranks disagree: {}", differences.join("; ")),
            })
        }
    }

    /// Broadcasts the values of `tensors` from rank 0 (initial weights).
    pub fn broadcast_from_zero(&self, tensors: &[Tensor], what: &str) -> Result<()> {
        for tensor in tensors {
            // Gloo and NCCL broadcast contiguous tensors in place; parameters are contiguous.
            let flat = if tensor.is_contiguous() { tensor.shallow_clone() } else { tensor.f_contiguous()? };
            self.broadcast(&flat, 0, what)?;
            if !tensor.is_contiguous() {
                tch::no_grad(|| tensor.shallow_clone().f_copy_(&flat))?;
            }
        }
        Ok(())
    }
}

impl Drop for ProcessGroup {
    fn drop(&mut self) {
        if let Some((stop, thread)) = self.heartbeat.take() {
            stop.store(true, Ordering::Relaxed);
            let _ = thread.join();
        }
        if self.failed.get() {
            // After a failed collective the backend's threads may still wait on a dead peer;
            // destroying it could block the exit the error is about to cause.
            std::mem::forget(self.group.take());
            std::mem::forget(self.store.take());
        }
    }
}

fn now_seconds() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs())
}
