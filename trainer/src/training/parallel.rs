//! The optimizer as the loop sees it, whatever the world size: one process (today's AdamW),
//! data parallel (AdamW after gradients are averaged over ranks in buckets) or ZeRO-2
//! ([`ShardedAdamW`]). All three give the same update for the same global batch.

use std::path::Path;

use tch::Tensor;

use super::{AdamW, CogNvsModel, PretrainConfig, trainable_parameters};
use crate::distributed::{GradientBuckets, ProcessGroup, ShardedAdamW};
use crate::error::Result;
use crate::weights::WrittenFile;

/// The run's optimizer and, with several ranks, how gradients meet.
pub(super) enum StepOptimizer {
    /// One process, or ZeRO stage 0: full AdamW state on every rank.
    Replicated { adamw: AdamW, buckets: Option<GradientBuckets> },
    /// ZeRO stage 2.
    Sharded(ShardedAdamW),
}

impl StepOptimizer {
    /// The optimizer for `model`'s trainable parameters (still fp32 here).
    pub(super) fn new(model: &CogNvsModel, config: &PretrainConfig, pg: Option<&ProcessGroup>) -> Result<Self> {
        let d = &config.distributed;
        Ok(match pg {
            Some(pg) if d.zero_stage == 2 => Self::Sharded(ShardedAdamW::new(
                trainable_parameters(model.trainable()),
                config.optim.clone(),
                d.bucket_mib,
                pg,
            )?),
            _ => Self::Replicated {
                adamw: AdamW::new(model.trainable(), config.optim.clone()),
                buckets: pg.map(|_| GradientBuckets::new(trainable_parameters(model.trainable()), d.bucket_mib)),
            },
        })
    }

    /// Loads the optimizer state of checkpoint `dir` (written at any world size and stage).
    pub(super) fn load(&mut self, dir: &Path, with_params: bool, pg: Option<&ProcessGroup>) -> Result<()> {
        match (self, pg) {
            (Self::Sharded(sharded), Some(pg)) => sharded.load(dir, pg, with_params),
            (Self::Replicated { adamw, .. }, _) => adamw.load(&dir.join("optimizer.safetensors"), with_params),
            (Self::Sharded(_), None) => unreachable!("ZeRO-2 runs have a process group"),
        }
    }

    /// Mixed precision: fp32 master weights (ZeRO-2 shards always hold them).
    pub(super) fn keep_master_weights(&mut self) -> Result<()> {
        match self {
            Self::Replicated { adamw, .. } => adamw.keep_master_weights(),
            Self::Sharded(_) => Ok(()),
        }
    }

    pub(super) fn zero_grad(&self) {
        match self {
            Self::Replicated { adamw, .. } => adamw.zero_grad(),
            Self::Sharded(sharded) => sharded.zero_grad(),
        }
    }

    /// Gradients over ranks, clipping on the global norm, the update. Returns the norm.
    pub(super) fn step(&mut self, lr: f64, max_norm: f64, pg: Option<&ProcessGroup>) -> Result<f64> {
        match self {
            Self::Replicated { adamw, buckets } => {
                if let (Some(buckets), Some(pg)) = (buckets.as_ref(), pg) {
                    buckets.average(pg)?;
                }
                let norm = adamw.clip_grad_norm(max_norm)?;
                adamw.step(lr)?;
                Ok(norm)
            }
            Self::Sharded(sharded) => sharded.step(pg.expect("ZeRO-2 runs have a process group"), lr),
        }
    }

    /// The fp32 master weights when they differ from the parameters (mixed precision, ZeRO-2);
    /// every rank takes part under ZeRO-2.
    pub(super) fn master_weights(&self, pg: Option<&ProcessGroup>) -> Result<Option<Vec<(String, Tensor)>>> {
        match (self, pg) {
            (Self::Replicated { adamw, .. }, _) => Ok(adamw.master_weights()),
            (Self::Sharded(sharded), Some(pg)) => Ok(Some(sharded.gather_masters(pg)?)),
            (Self::Sharded(_), None) => unreachable!("ZeRO-2 runs have a process group"),
        }
    }

    /// Writes the optimizer state into checkpoint folder `dir`: rank 0's `optimizer.safetensors`
    /// (replicated state), or every rank's shard. Returns the files this rank wrote.
    pub(super) fn save(&self, dir: &Path, with_params: bool, rank: usize) -> Result<Vec<WrittenFile>> {
        match self {
            Self::Replicated { adamw, .. } if rank == 0 => {
                Ok(vec![adamw.save(&dir.join("optimizer.safetensors"), with_params)?])
            }
            Self::Replicated { .. } => Ok(Vec::new()),
            Self::Sharded(sharded) => Ok(vec![sharded.save(dir)?]),
        }
    }
}
