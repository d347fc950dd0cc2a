//! `trainer comm-cost`: how much of a data-parallel training step the gradient and weight
//! exchange costs. The config's model trains on random clips of its data shape, in rounds, each
//! round timing a few steps of every variant in turn (ZeRO-0 and ZeRO-2, each with the real
//! collectives and with `[distributed] noop_collectives`), so a machine's changing load falls on
//! all variants alike. The exposed communication of a stage is its step time with the real
//! collectives less the step time with local no-ops (the same arithmetic), as a share of the
//! former: what overlapping the exchange with the backward has not hidden.

use std::time::Instant;

use serde::Serialize;
use tch::{Device, Kind, Tensor};

use super::parallel::StepOptimizer;
use super::{Backward, CogNvsModel, Draws, PretrainConfig, learning_rate};
use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};
use crate::training::data::{Batch, DataPosition};

/// The ZeRO stages compared.
const STAGES: [u8; 2] = [0, 2];
/// Steps a fresh optimizer takes before the timed ones (its first allocates its state).
const WARM_UP_STEPS: usize = 1;

/// How long one variant's steps took.
#[derive(Debug, Clone, Serialize)]
pub struct VariantTiming {
    /// `[distributed] zero_stage`.
    pub zero_stage: u8,
    /// `real` or `noop` collectives.
    pub collectives: &'static str,
    /// Median over the timed steps of all rounds, in seconds (rank 0's clock).
    pub median_step_seconds: f64,
    /// Every timed step, in seconds, round after round.
    pub step_seconds: Vec<f64>,
}

/// What [`comm_cost`] measured (printed by `trainer comm-cost` as one JSON line).
#[derive(Debug, Clone, Serialize)]
pub struct CommCost {
    /// Ranks.
    pub world_size: usize,
    /// `gloo` or `nccl`.
    pub backend: &'static str,
    /// The compute device of rank 0.
    pub device: String,
    /// Trainable parameters.
    pub trainable_parameters: i64,
    /// `[distributed] bucket_mib`.
    pub bucket_mib: f64,
    /// `[loop] gradient_checkpointing`.
    pub gradient_checkpointing: bool,
    /// Timed steps per variant and round.
    pub steps: usize,
    /// Rounds.
    pub rounds: usize,
    /// One entry per variant, in the order they ran within a round.
    pub variants: Vec<VariantTiming>,
    /// Per ZeRO stage (`zero0`, `zero2`): (real − noop) / real of the median step times.
    pub exposed_fraction: std::collections::BTreeMap<String, f64>,
    /// Median step of ZeRO-2 over ZeRO-0, both with real collectives.
    pub zero2_over_zero0: f64,
}

/// Times `steps` steps of each variant in each of `rounds` rounds on `pg` (see the module docs).
/// Every rank must call it with the same arguments.
pub fn comm_cost(
    config: &PretrainConfig,
    device: Device,
    pg: &ProcessGroup,
    steps: usize,
    rounds: usize,
) -> Result<CommCost> {
    config.validate("comm-cost config")?;
    let world = pg.world_size;
    if !config.data.batch_size.is_multiple_of(world) {
        return Err(Error::InvalidConfig {
            source_name: "comm-cost config".to_string(),
            field: "data.batch_size".to_string(),
            reason: format!("the global batch {} must be a multiple of the world size {world}", config.data.batch_size),
        });
    }
    let mut model = CogNvsModel::load(&config.model, config.lora.as_ref(), config.train.seed, device)?;
    let trainable: Vec<Tensor> = model.trainable().trainable_variables();
    tch::no_grad(|| pg.broadcast_from_zero(&trainable, "initial weights"))?;
    let trainable_parameters = trainable.iter().map(|t| t.numel() as i64).sum();
    let batch = random_batch(config, world, device)?;
    let draws = Draws { rank: pg.rank as i64, world: world as i64 };
    let kind = config.train.precision.kind(device);
    let variants: Vec<(u8, bool)> = STAGES.iter().flat_map(|&stage| [(stage, false), (stage, true)]).collect();
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    let mut step_index = 0u64;
    for _ in 0..rounds {
        for (v, &(zero_stage, noop)) in variants.iter().enumerate() {
            let mut variant = config.clone();
            variant.distributed.zero_stage = zero_stage;
            variant.distributed.noop_collectives = noop;
            // A fresh optimizer takes its fp32 state from fp32 weights, as a run does.
            model.set_kind(Kind::Float);
            let mut optimizer = StepOptimizer::new(&model, &variant, Some(pg))?;
            if kind != Kind::Float {
                optimizer.keep_master_weights()?;
                model.set_kind(kind);
            }
            for k in 0..WARM_UP_STEPS + steps {
                pg.barrier("comm-cost step")?;
                let started = Instant::now();
                train_step(&model, &mut optimizer, &variant, &batch, draws, step_index, pg)?;
                if let Device::Cuda(index) = device {
                    tch::Cuda::synchronize(index as i64);
                }
                let seconds = started.elapsed().as_secs_f64();
                step_index += 1;
                if k >= WARM_UP_STEPS {
                    times[v].push(seconds);
                }
            }
        }
    }
    let median = |values: &[f64]| {
        let mut sorted = values.to_vec();
        sorted.sort_by(f64::total_cmp);
        sorted[sorted.len() / 2]
    };
    let variants: Vec<VariantTiming> = variants
        .iter()
        .zip(times)
        .map(|(&(zero_stage, noop), step_seconds)| VariantTiming {
            zero_stage,
            collectives: if noop { "noop" } else { "real" },
            median_step_seconds: median(&step_seconds),
            step_seconds,
        })
        .collect();
    let median_of = |stage: u8, noop: bool| {
        variants
            .iter()
            .find(|v| v.zero_stage == stage && (v.collectives == "noop") == noop)
            .map_or(f64::NAN, |v| v.median_step_seconds)
    };
    let exposed_fraction = STAGES
        .iter()
        .map(|&stage| {
            let real = median_of(stage, false);
            (format!("zero{stage}"), (real - median_of(stage, true)) / real)
        })
        .collect();
    Ok(CommCost {
        world_size: world,
        backend: if device.is_cuda() { "nccl" } else { "gloo" },
        device: format!("{device:?}"),
        trainable_parameters,
        bucket_mib: config.distributed.bucket_mib,
        gradient_checkpointing: config.train.gradient_checkpointing,
        steps,
        rounds,
        zero2_over_zero0: median_of(2, false) / median_of(0, false),
        exposed_fraction,
        variants,
    })
}

/// One optimizer step as `trainer pretrain` takes it: the micro-batches' forward and backward,
/// the loss summed over ranks, the exchange and the update.
fn train_step(
    model: &CogNvsModel,
    optimizer: &mut StepOptimizer,
    config: &PretrainConfig,
    batch: &Batch,
    draws: Draws,
    step: u64,
    pg: &ProcessGroup,
) -> Result<()> {
    tch::manual_seed(config.train.seed as i64 ^ step as i64);
    optimizer.zero_grad()?;
    let accumulation = config.optim.grad_accumulation;
    let mut loss = 0.0;
    for micro_batch in 1..=accumulation {
        let mut exchange = |stage| optimizer.backward_stage_done(stage, Some(pg));
        let backward = Backward {
            checkpointing: config.train.gradient_checkpointing,
            on_stage: (micro_batch == accumulation).then_some(&mut exchange as _),
        };
        loss += model.loss_backward(
            batch,
            (config.train.condition_noise_log_mean, config.train.condition_noise_log_std),
            None,
            accumulation as f64,
            backward,
            draws,
        )?;
    }
    let loss = pg.sum_f64(loss, "loss")?;
    if !loss.is_finite() {
        return Err(Error::InvalidArgument {
            name: "loss".to_string(),
            reason: format!("non-finite loss {loss} at comm-cost step {}", step + 1),
        });
    }
    let lr = learning_rate(&config.optim, step, config.train.steps);
    optimizer.step(lr, config.optim.max_grad_norm, Some(pg))?;
    Ok(())
}

/// A batch of uniform random clips in [-1, 1] of the config's data shape, this rank's share of
/// the global batch.
fn random_batch(config: &PretrainConfig, world: usize, device: Device) -> Result<Batch> {
    let d = &config.data;
    let b = (d.batch_size / world) as i64;
    let shape = [b, 3, d.frames as i64, i64::from(d.height), i64::from(d.width)];
    let clip = || -> Result<Tensor> {
        Ok(Tensor::f_rand(shape, (Kind::Float, device))?.f_mul_scalar(2.0)?.f_sub_scalar(1.0)?)
    };
    Ok(Batch {
        target: clip()?,
        condition: clip()?,
        mask: Tensor::f_ones([b, 1, shape[2], shape[3], shape[4]], (Kind::Float, device))?,
        provenance: (0..b).map(|i| format!("random clip {i}")).collect(),
        position: DataPosition::default(),
    })
}
