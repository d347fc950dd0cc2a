//! Checkpoints: `RUN/checkpoints/step-NNNNNNNN/` with the transformer in the diffusers layout,
//! the optimizer state and `state.json`, written under a temporary name and renamed.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use super::CogNvsModel;
use super::parallel::StepOptimizer;
use crate::cogvideox_transformer_3d as transformer;
use crate::data::DataPosition;
use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};
use crate::weights;

/// `state.json` of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Optimizer steps done.
    pub step: u64,
    /// The data position of the next batch.
    pub data_position: DataPosition,
    /// The run seed.
    pub seed: u64,
    /// How the ranks that wrote the checkpoint shared the optimizer state (absent: one process).
    /// Any world size and stage resumes from any checkpoint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<CheckpointLayout>,
}

/// The world that wrote a checkpoint.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CheckpointLayout {
    /// Ranks.
    pub world_size: usize,
    /// ZeRO stage (0: `optimizer.safetensors`; 2: one `optimizer-rank-R-of-N.safetensors` per rank).
    pub zero_stage: u8,
}

fn checkpoints_dir(run: &Path) -> PathBuf {
    run.join("checkpoints")
}

/// The checkpoints of a run, oldest first.
pub fn list_checkpoints(run: &Path) -> Vec<(u64, PathBuf)> {
    let mut found: Vec<(u64, PathBuf)> = std::fs::read_dir(checkpoints_dir(run))
        .into_iter()
        .flatten()
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let step = name.strip_prefix("step-")?.parse().ok()?;
            e.path().join("state.json").is_file().then(|| (step, e.path()))
        })
        .collect();
    found.sort();
    found
}

pub(super) fn save_checkpoint(
    run: &Path,
    model: &CogNvsModel,
    optimizer: &StepOptimizer,
    state: &TrainState,
    keep: usize,
    pg: Option<&ProcessGroup>,
) -> Result<PathBuf> {
    let dir = checkpoints_dir(run);
    let final_dir = dir.join(format!("step-{:08}", state.step));
    let temp = dir.join(format!(".tmp-step-{:08}", state.step));
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| Error::Io { path, error: source }
    };
    let rank = pg.map_or(0, |pg| pg.rank);
    // fp32 throughout: a mixed-precision run's master weights replace its bf16 parameters
    // (under ZeRO-2 every rank takes part in gathering them).
    let masters: BTreeMap<String, Tensor> = optimizer.master_weights(pg)?.into_iter().flatten().collect();
    if rank == 0 {
        let _ = std::fs::remove_dir_all(&temp);
        std::fs::create_dir_all(&temp).map_err(io(&temp))?;
    }
    if let Some(pg) = pg {
        pg.barrier("checkpoint folder created")?;
    }
    // A LoRA run keeps its adapters' exact values here too (the LoRA file holds B scaled).
    optimizer.save(&temp, model.lora_vs.is_some())?;
    if let Some(pg) = pg {
        // Every shard is in before rank 0 marks the checkpoint complete.
        pg.barrier("optimizer state written")?;
    }
    if rank != 0 {
        if let Some(pg) = pg {
            pg.barrier("checkpoint complete")?;
        }
        return Ok(final_dir);
    }
    match (&model.lora_vs, &model.lora) {
        (Some(lora_vs), Some(lora)) => {
            crate::lora::save(lora_vs, &masters, lora.scale(), &temp.join(crate::lora::LORA_WEIGHTS_NAME))?;
        }
        _ => {
            let mut variables: BTreeMap<String, Tensor> = model.vs.variables().into_iter().collect();
            variables.extend(masters);
            let variables = variables
                .into_iter()
                .map(|(name, t)| Ok((name, if t.is_floating_point() { t.f_to_kind(Kind::Float)? } else { t })))
                .collect::<Result<_>>()?;
            weights::save_tensors(
                variables,
                model.transformer.config(),
                transformer::CLASS_NAME,
                &temp.join("transformer"),
                weights::DEFAULT_MAX_SHARD_BYTES,
            )?;
        }
    }
    let json = serde_json::to_vec_pretty(state).expect("state serialises");
    std::fs::write(temp.join("state.json"), json).map_err(io(&temp))?;
    let _ = std::fs::remove_dir_all(&final_dir);
    std::fs::rename(&temp, &final_dir).map_err(io(&final_dir))?;
    let all = list_checkpoints(run);
    for (_, old) in all.iter().take(all.len().saturating_sub(keep)) {
        let _ = std::fs::remove_dir_all(old);
    }
    if let Some(pg) = pg {
        pg.barrier("checkpoint complete")?;
    }
    Ok(final_dir)
}
