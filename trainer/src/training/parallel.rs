//! The optimizer as the loop sees it, whatever the world size: one process, data parallel
//! (ZeRO-0) or ZeRO-2, all [`AdamW`] over flat buckets laid out in the order the transformer's
//! backward finishes its gradients, so that with several ranks each bucket's reduction starts
//! while the backward goes on (see `crate::distributed`'s data parallelism). All three give the
//! same update for the same global batch.

use std::path::Path;

use tch::Tensor;

use super::{AdamW, CogNvsModel, PretrainConfig, trainable_parameters};
use crate::distributed::{FlatLayout, GradientExchange, ProcessGroup};
use crate::error::Result;
use crate::models::weights::WrittenFile;

/// The run's optimizer and, with several ranks, how gradients meet.
pub(super) struct StepOptimizer {
    adamw: AdamW,
}

impl StepOptimizer {
    /// The optimizer for `model`'s trainable parameters (still fp32 here): ZeRO-2 when the
    /// config asks for it and there are ranks, else every rank holds the whole state.
    pub(super) fn new(model: &CogNvsModel, config: &PretrainConfig, pg: Option<&ProcessGroup>) -> Result<Self> {
        let d = &config.distributed;
        let params = trainable_parameters(model.trainable());
        let (rank, world) = pg.map_or((0, 1), |pg| (pg.rank, pg.world_size));
        let sharded = pg.is_some() && d.zero_stage == 2;
        let transformer = &model.transformer;
        let layout =
            FlatLayout::new(&params, |name| transformer.backward_stage_of(name), d.bucket_mib, rank, world, sharded);
        let exchange = pg.map(|_| GradientExchange::new(layout.bucket_count(), d.noop_collectives));
        Ok(Self { adamw: AdamW::with_layout(params, config.optim.clone(), layout, exchange)? })
    }

    /// Loads the optimizer state of checkpoint `dir` (written at any world size and stage).
    pub(super) fn load(&mut self, dir: &Path, with_params: bool, pg: Option<&ProcessGroup>) -> Result<()> {
        self.adamw.load(dir, with_params, pg)
    }

    /// Mixed precision: fp32 master weights (ZeRO-2 shards always hold them).
    pub(super) fn keep_master_weights(&mut self) -> Result<()> {
        self.adamw.keep_master_weights()
    }

    /// Zeroes the gradients before a step's first micro-batch.
    pub(super) fn zero_grad(&mut self) -> Result<()> {
        self.adamw.zero_grad()
    }

    /// What the last micro-batch's backward calls after each of its stages (see
    /// `CogNvsModel::loss_backward`): the buckets that are final start their reduction.
    pub(super) fn backward_stage_done(&mut self, stage: usize, pg: Option<&ProcessGroup>) -> Result<()> {
        self.adamw.backward_stage_done(stage, pg)
    }

    /// Gradients over ranks, clipping on the global norm, the update. Returns the norm.
    pub(super) fn step(&mut self, lr: f64, max_norm: f64, pg: Option<&ProcessGroup>) -> Result<f64> {
        self.adamw.step(lr, max_norm, pg)
    }

    /// The fp32 master weights when they differ from the parameters (mixed precision, ZeRO-2);
    /// every rank takes part under ZeRO-2.
    pub(super) fn master_weights(&self, pg: Option<&ProcessGroup>) -> Result<Option<Vec<(String, Tensor)>>> {
        self.adamw.master_weights(pg)
    }

    /// Writes the optimizer state into checkpoint folder `dir`: rank 0's `optimizer.safetensors`
    /// (replicated state), or every rank's shard. Returns the files this rank wrote.
    pub(super) fn save(&self, dir: &Path, with_params: bool) -> Result<Vec<WrittenFile>> {
        Ok(self.adamw.save(dir, with_params)?.into_iter().collect())
    }
}
