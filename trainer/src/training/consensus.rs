//! What the ranks of a job decide together, in one small collective each: whether any rank saw a
//! flag (a preemption signal, a failed write), sums of a few numbers (validation metrics), and
//! every rank's short text (the digests of the files each rank wrote, the problems each found).
//! With one process (`pg` None) each is the process's own value.

use tch::{Device, Kind, Tensor};

use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};

/// The sums over ranks of `values`, reduced in f64 in one all-reduce.
pub fn sum_over_ranks(pg: Option<&ProcessGroup>, values: &[f64], what: &str) -> Result<Vec<f64>> {
    let Some(pg) = pg else { return Ok(values.to_vec()) };
    let tensor = Tensor::from_slice(values).f_to_device(pg.device())?;
    pg.all_reduce_sum(&tensor, what)?;
    Ok(Vec::<f64>::try_from(tensor.f_to_device(Device::Cpu)?)?)
}

/// For each flag, whether any rank raised it: every rank gets the same answer.
pub fn any_rank<const N: usize>(pg: Option<&ProcessGroup>, flags: [bool; N], what: &str) -> Result<[bool; N]> {
    let sums = sum_over_ranks(pg, &flags.map(|f| f64::from(u8::from(f))), what)?;
    Ok(std::array::from_fn(|i| sums[i] > 0.0))
}

/// Every rank's `text`, in rank order (two all-gathers: the lengths, then the padded bytes).
pub fn gather_text(pg: Option<&ProcessGroup>, text: &str, what: &str) -> Result<Vec<String>> {
    let Some(pg) = pg else { return Ok(vec![text.to_string()]) };
    let world = pg.world_size as i64;
    let device = pg.device();
    let length = Tensor::from_slice(&[text.len() as i64]).f_to_device(device)?;
    let lengths = Tensor::f_zeros([world], (Kind::Int64, device))?;
    pg.wait(pg.all_gather_start(&lengths, &length, &format!("{what}: lengths"))?)?;
    let lengths = Vec::<i64>::try_from(lengths.f_to_device(Device::Cpu)?)?;
    let longest = lengths.iter().copied().max().unwrap_or(0).max(1);
    let mut padded = text.as_bytes().to_vec();
    padded.resize(longest as usize, 0);
    let mine = Tensor::from_slice(&padded).f_to_device(device)?;
    let all = Tensor::f_zeros([world * longest], (Kind::Uint8, device))?;
    pg.wait(pg.all_gather_start(&all, &mine, what)?)?;
    let bytes = Vec::<u8>::try_from(all.f_to_device(Device::Cpu)?)?;
    lengths
        .iter()
        .enumerate()
        .map(|(rank, &len)| {
            let start = rank * longest as usize;
            String::from_utf8(bytes[start..start + len as usize].to_vec()).map_err(|e| Error::Distributed {
                rank: pg.rank,
                world_size: pg.world_size,
                what: what.to_string(),
                reason: format!("rank {rank} sent text that is not UTF-8: {e}"),
            })
        })
        .collect()
}
