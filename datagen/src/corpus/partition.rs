//! Splitting a corpus across machines: a stable hash partition of input keys that is disjoint and
//! complete for any worker count, with worker count and index defaulting from the scheduler's
//! environment (Slurm job arrays, Kubernetes indexed jobs).

use crate::error::{Error, Result};

/// Which worker of how many this process is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Worker {
    /// Total number of workers (≥ 1).
    pub count: u32,
    /// This worker's index, `0..count`.
    pub index: u32,
}

impl Worker {
    /// The single worker of an unpartitioned run.
    pub const SOLE: Self = Self { count: 1, index: 0 };

    /// Builds and checks a worker, naming the offending flag.
    pub fn new(count: u32, index: u32) -> Result<Self> {
        if count == 0 {
            return Err(Error::parameter("num-workers", "must be at least 1"));
        }
        if index >= count {
            return Err(Error::parameter("worker-index", format!("{index} is not below --num-workers {count}")));
        }
        Ok(Self { count, index })
    }

    /// Worker from explicit flags, else from the environment: `SLURM_ARRAY_TASK_COUNT` +
    /// `SLURM_ARRAY_TASK_ID` (minus `SLURM_ARRAY_TASK_MIN`, so arrays need not start at 0), or
    /// `JOB_COMPLETION_INDEX` with `--num-workers` (Kubernetes indexed jobs give no count), else
    /// the sole worker.
    pub fn from_flags_or_env(
        count: Option<u32>,
        index: Option<u32>,
        env: impl Fn(&str) -> Option<String>,
    ) -> Result<Self> {
        let parse = |name: &str| -> Result<Option<u32>> {
            env(name)
                .map(|v| {
                    v.trim()
                        .parse::<u32>()
                        .map_err(|_| Error::parameter(name, format!("`{v}` is not a non-negative integer")))
                })
                .transpose()
        };
        let count = match count {
            Some(count) => Some(count),
            None => parse("SLURM_ARRAY_TASK_COUNT")?,
        };
        let index = match index {
            Some(index) => Some(index),
            None => match (parse("SLURM_ARRAY_TASK_ID")?, parse("JOB_COMPLETION_INDEX")?) {
                (Some(id), _) => Some(id - parse("SLURM_ARRAY_TASK_MIN")?.unwrap_or(0).min(id)),
                (None, Some(id)) => Some(id),
                (None, None) => None,
            },
        };
        match (count, index) {
            (None, None) => Ok(Self::SOLE),
            (Some(count), index) => Self::new(count, index.unwrap_or(0)),
            (None, Some(index)) => {
                Err(Error::parameter("num-workers", format!("worker index {index} given without a worker count")))
            }
        }
    }

    /// Whether the input with stable key `key` belongs to this worker.
    pub fn owns(&self, key: &str) -> bool {
        worker_of(key, self.count) == self.index
    }
}

/// The worker (of `count`) that owns `key`: the first 8 bytes of its BLAKE3 hash modulo `count`.
/// Depends only on the key, never on listing order or machine.
pub fn worker_of(key: &str, count: u32) -> u32 {
    let hash = blake3::hash(key.as_bytes());
    let prefix = u64::from_le_bytes(hash.as_bytes()[..8].try_into().expect("8 bytes"));
    (prefix % u64::from(count.max(1))) as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partition_is_disjoint_complete_and_balanced() {
        let keys: Vec<String> = (0..3000).map(|i| format!("sav/sav_{i:06}")).collect();
        for count in [1, 2, 3, 7] {
            let mut owners = vec![0u32; count as usize];
            for key in &keys {
                let owning: Vec<u32> = (0..count).filter(|&i| Worker::new(count, i).unwrap().owns(key)).collect();
                assert_eq!(owning.len(), 1, "{key} owned by exactly one of {count}");
                owners[owning[0] as usize] += 1;
            }
            let expected = keys.len() as f64 / count as f64;
            assert!(owners.iter().all(|&n| (n as f64 - expected).abs() < 0.15 * expected + 10.0), "{owners:?}");
        }
    }

    #[test]
    fn environment_defaults() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |name: &str| pairs.iter().find(|(k, _)| *k == name).map(|(_, v)| v.to_string())
        };
        assert_eq!(Worker::from_flags_or_env(None, None, env(&[])).unwrap(), Worker::SOLE);
        let slurm =
            env(&[("SLURM_ARRAY_TASK_COUNT", "4"), ("SLURM_ARRAY_TASK_ID", "6"), ("SLURM_ARRAY_TASK_MIN", "3")]);
        assert_eq!(Worker::from_flags_or_env(None, None, slurm).unwrap(), Worker { count: 4, index: 3 });
        let k8s = env(&[("JOB_COMPLETION_INDEX", "2")]);
        assert_eq!(Worker::from_flags_or_env(Some(5), None, k8s).unwrap(), Worker { count: 5, index: 2 });
        assert!(Worker::from_flags_or_env(None, None, k8s).unwrap_err().to_string().contains("num-workers"));
        assert!(
            Worker::from_flags_or_env(Some(2), Some(2), env(&[])).unwrap_err().to_string().contains("worker-index")
        );
        let bad = env(&[("SLURM_ARRAY_TASK_COUNT", "x")]);
        assert!(Worker::from_flags_or_env(None, None, bad).unwrap_err().to_string().contains("SLURM_ARRAY_TASK_COUNT"));
    }
}
