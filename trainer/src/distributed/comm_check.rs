//! `trainer comm-check`: the collectives the training exchange uses, checked for exact results
//! on every rank (broadcast, all-reduce, reduce-scatter, all-gather, barrier), and the
//! all-reduce bandwidth in nccl-tests' conventions. What a cluster's backend is worth before a
//! long run relies on it; `training::comm_cost` measures the exchange's share of a real step.

use std::fmt;
use std::time::Instant;

use tch::{Device, Kind, Tensor};

use super::ProcessGroup;
use crate::error::{Error, Result};

/// Runs each collective on small tensors whose exact result every rank knows, and tells
/// `passed` the name of each one that gave it (on every rank). An error names the rank and the
/// collective that gave a wrong result.
pub fn check_collectives(pg: &ProcessGroup, device: Device, mut passed: impl FnMut(&str)) -> Result<()> {
    let (rank, world) = (pg.rank as i64, pg.world_size as i64);
    let options = (Kind::Float, device);
    let wrong = |what: &str, got: &Tensor| Error::Distributed {
        rank: pg.rank,
        world_size: pg.world_size,
        what: what.to_string(),
        reason: format!("wrong result {got}"),
    };
    // Broadcast: rank 0's values everywhere.
    let value = Tensor::full([1000], rank as f64 + 7.0, options);
    pg.broadcast(&value, 0, "check")?;
    if value.min().double_value(&[]) != 7.0 {
        return Err(wrong("broadcast", &value.min()));
    }
    passed("broadcast");
    // All-reduce: Σ (r + 1) over ranks.
    let value = Tensor::full([1000], rank as f64 + 1.0, options);
    pg.all_reduce_sum(&value, "check")?;
    if value.max().double_value(&[]) != (world * (world + 1) / 2) as f64 {
        return Err(wrong("all-reduce", &value.max()));
    }
    passed("all-reduce");
    // Reduce-scatter: element i of the input is i + r; this rank's slice of the sum.
    let chunk = 5;
    let input = Tensor::arange(chunk * world, options).f_add_scalar(rank as f64)?;
    let output = Tensor::zeros([chunk], options);
    pg.wait(pg.reduce_scatter_sum_start(&output, &input, "check")?)?;
    let expected = Tensor::arange_start(rank * chunk, (rank + 1) * chunk, options)
        .f_mul_scalar(world as f64)?
        .f_add_scalar((world * (world - 1) / 2) as f64)?;
    if !output.allclose(&expected, 0.0, 0.0, false) {
        return Err(wrong("reduce-scatter", &output));
    }
    passed("reduce-scatter");
    // All-gather: every rank's constant block in rank order.
    let input = Tensor::full([chunk], rank as f64, options);
    let output = Tensor::zeros([chunk * world], options);
    pg.wait(pg.all_gather_start(&output, &input, "check")?)?;
    let expected = Tensor::arange(world, options).f_repeat_interleave_self_int(chunk, None::<i64>, None::<i64>)?;
    if !output.allclose(&expected, 0.0, 0.0, false) {
        return Err(wrong("all-gather", &output));
    }
    passed("all-gather");
    pg.barrier("check")?;
    passed("barrier");
    Ok(())
}

/// Timings of repeated all-reduces of one payload.
#[derive(Debug, Clone)]
pub struct Bandwidth {
    /// Payload in MiB.
    pub mib: u64,
    /// Ranks.
    pub world_size: usize,
    /// The device the tensors lived on.
    pub device: Device,
    /// Seconds of each all-reduce, sorted.
    pub seconds: Vec<f64>,
}

impl Bandwidth {
    /// The median all-reduce time in seconds.
    pub fn median(&self) -> f64 {
        self.seconds[self.seconds.len() / 2]
    }

    /// The bus bandwidth in MiB/s, nccl-tests' convention: 2·(N−1)/N of the payload crosses
    /// each link.
    pub fn bus_mib_per_second(&self) -> f64 {
        let world = self.world_size as f64;
        2.0 * (world - 1.0) / world * self.mib as f64 / self.median()
    }
}

impl fmt::Display for Bandwidth {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (first, last) = (self.seconds[0], self.seconds[self.seconds.len() - 1]);
        write!(
            f,
            "all-reduce {} MiB over {} ranks ({:?}): median {:.1} ms (range {:.1}-{:.1}), algorithm bandwidth {:.0} MiB/s, bus bandwidth {:.0} MiB/s",
            self.mib,
            self.world_size,
            self.device,
            self.median() * 1e3,
            first * 1e3,
            last * 1e3,
            self.mib as f64 / self.median(),
            self.bus_mib_per_second()
        )
    }
}

/// Times `iterations` (≥ 1) all-reduces of `mib` MiB after one warm-up, each between barriers;
/// on CUDA the device is synchronised around each, so the time is what the device did (NCCL's
/// wait orders the stream, not the host).
pub fn all_reduce_bandwidth(pg: &ProcessGroup, device: Device, mib: u64, iterations: usize) -> Result<Bandwidth> {
    if iterations == 0 {
        return Err(Error::InvalidArgument { name: "iterations".to_string(), reason: "must be ≥ 1".to_string() });
    }
    let elements = (mib * 1024 * 1024 / 4) as i64;
    let big = Tensor::ones([elements], (Kind::Float, device));
    pg.all_reduce_sum(&big, "warm-up")?;
    let synchronize = || {
        if let Device::Cuda(index) = device {
            tch::Cuda::synchronize(index as i64);
        }
    };
    let mut seconds = Vec::with_capacity(iterations);
    for _ in 0..iterations {
        pg.barrier("bandwidth")?;
        synchronize();
        let started = Instant::now();
        pg.all_reduce_sum(&big, "bandwidth")?;
        synchronize();
        seconds.push(started.elapsed().as_secs_f64());
    }
    seconds.sort_by(f64::total_cmp);
    Ok(Bandwidth { mib, world_size: pg.world_size, device, seconds })
}

/// `trainer comm-check`: joins the process group the launcher describes (a world of one
/// included: a backend check on one GPU), checks every collective and measures the all-reduce
/// bandwidth of `mib` MiB over `iterations`; `line` hears rank 0's report lines. Without
/// launcher variables there is nothing to check: one line says so.
pub fn run_launched(
    device: Device,
    timeout_seconds: f64,
    mib: u64,
    iterations: usize,
    mut line: impl FnMut(&str),
) -> Result<()> {
    let launch = super::Launch::from_env_any_size()?;
    let (device, pg) = super::join(launch, device, timeout_seconds)?;
    let Some(pg) = pg else {
        line("no launcher variables (torchrun, srun, RANK/WORLD_SIZE): nothing to check");
        return Ok(());
    };
    let lead = pg.rank == 0;
    check_collectives(&pg, device, |name| {
        if lead {
            line(&format!("{name} ok"))
        }
    })?;
    let bandwidth = all_reduce_bandwidth(&pg, device, mib, iterations)?;
    if lead {
        line(&bandwidth.to_string());
    }
    Ok(())
}
