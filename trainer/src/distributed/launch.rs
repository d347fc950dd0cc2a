//! Who this process is in a multi-process job, read from what the launcher set: torchrun
//! (`RANK`, `WORLD_SIZE`, `LOCAL_RANK`, `MASTER_ADDR`, `MASTER_PORT`, and the elastic agent's
//! `TORCHELASTIC_USE_AGENT_STORE` / `TORCHELASTIC_RESTART_COUNT`), Slurm `srun` (`SLURM_PROCID`,
//! `SLURM_NTASKS`, `SLURM_LOCALID`, the first host of `SLURM_JOB_NODELIST`), or the same variables
//! as torchrun's set by hand. No variables, or a world size of 1, is a single process.

use crate::error::{Error, Result};

/// The rendezvous port when neither `MASTER_PORT` nor a Slurm job id gives one (torchrun's).
pub const DEFAULT_MASTER_PORT: u16 = 29500;
/// Slurm jobs without `MASTER_PORT` take a port from their job id in this range, so two jobs
/// sharing a first node do not collide: `SLURM_PORT_BASE + job_id % SLURM_PORT_SPAN`.
const SLURM_PORT_BASE: u16 = 20000;
/// See [`SLURM_PORT_BASE`].
const SLURM_PORT_SPAN: u64 = 20000;

/// Which launcher started the process.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Launcher {
    /// torchrun's elastic agent (it hosts the store itself).
    Torchrun,
    /// Slurm `srun`.
    Slurm,
    /// `RANK`/`WORLD_SIZE` set by hand (rank 0 hosts the store).
    Env,
}

/// This process's place in the job.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Launch {
    /// Global rank.
    pub rank: usize,
    /// Number of processes.
    pub world_size: usize,
    /// Rank on this machine: the CUDA device index.
    pub local_rank: usize,
    /// Host of the rendezvous store.
    pub master_addr: String,
    /// Port of the rendezvous store.
    pub master_port: u16,
    /// Who started us.
    pub launcher: Launcher,
    /// Under torchrun: every rank connects to the agent's store, under this key prefix (one per
    /// restart, so a restarted job never reads the previous attempt's keys).
    pub agent_store_prefix: Option<String>,
}

impl Launch {
    /// Reads the launcher variables of this process's environment. `Ok(None)`: a single process.
    pub fn from_env() -> Result<Option<Self>> {
        Self::from_vars(|name| std::env::var(name).ok())
    }

    /// As [`Self::from_env`], but a launcher's world size of 1 is a job too (for checking a
    /// backend, e.g. NCCL, on a single GPU).
    pub fn from_env_any_size() -> Result<Option<Self>> {
        Self::read(|name| std::env::var(name).ok(), true)
    }

    /// As [`Self::from_env`] with the variables from `var`.
    pub fn from_vars(var: impl Fn(&str) -> Option<String>) -> Result<Option<Self>> {
        Self::read(var, false)
    }

    fn read(var: impl Fn(&str) -> Option<String>, keep_single: bool) -> Result<Option<Self>> {
        let bad = |name: &str, reason: String| Error::Launcher { variable: name.to_string(), reason };
        let number = |name: &str| number(&var, name);
        let Some(Ranks { rank, world_size, local_rank, launcher }) = Ranks::read(&var)? else { return Ok(None) };
        if world_size == 1 && !keep_single {
            return Ok(None);
        }
        let master_addr = match (var("MASTER_ADDR"), launcher) {
            (Some(addr), _) if !addr.trim().is_empty() => addr.trim().to_string(),
            _ if world_size == 1 => "127.0.0.1".to_string(),
            (_, Launcher::Slurm) => {
                let list = var("SLURM_JOB_NODELIST").or_else(|| var("SLURM_NODELIST")).ok_or_else(|| {
                    bad(
                        "MASTER_ADDR",
                        "unset, and neither SLURM_JOB_NODELIST nor SLURM_NODELIST names the hosts".into(),
                    )
                })?;
                first_host(&list).ok_or_else(|| bad("SLURM_JOB_NODELIST", format!("`{list}` names no host")))?
            }
            _ => {
                return Err(bad(
                    "MASTER_ADDR",
                    format!("unset with WORLD_SIZE {world_size}: set it to the host of rank 0 (and MASTER_PORT)"),
                ));
            }
        };
        let master_port = match var("MASTER_PORT") {
            Some(text) => match text.trim().parse::<u16>() {
                Ok(port) if port > 0 => port,
                _ => return Err(bad("MASTER_PORT", format!("`{text}` is not a port in 1..=65535"))),
            },
            None if launcher == Launcher::Slurm => match number("SLURM_JOB_ID")? {
                Some(job) => SLURM_PORT_BASE + (job as u64 % SLURM_PORT_SPAN) as u16,
                None => DEFAULT_MASTER_PORT,
            },
            None => DEFAULT_MASTER_PORT,
        };
        let agent_store = launcher == Launcher::Torchrun
            && var("TORCHELASTIC_USE_AGENT_STORE").is_some_and(|v| v.eq_ignore_ascii_case("true"));
        let agent_store_prefix = agent_store.then(|| {
            // torch.distributed's own prefix for the default group under the agent's store.
            format!("/worker/attempt_{}", var("TORCHELASTIC_RESTART_COUNT").unwrap_or_else(|| "0".to_string()))
        });
        Ok(Some(Self { rank, world_size, local_rank, master_addr, master_port, launcher, agent_store_prefix }))
    }
}

/// Rank, world size, local rank and launcher: the part of the launcher variables every reader
/// needs (the memory plan needs only the world size; joining a job needs the rendezvous too).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Ranks {
    rank: usize,
    world_size: usize,
    local_rank: usize,
    launcher: Launcher,
}

impl Ranks {
    /// The ranks the variables from `var` give, checked; `Ok(None)`: no launcher variables.
    fn read(var: &impl Fn(&str) -> Option<String>) -> Result<Option<Self>> {
        let bad = |name: &str, reason: String| Error::Launcher { variable: name.to_string(), reason };
        let number = |name: &str| number(var, name);
        let (rank, world_size, local_rank, launcher) = if var("RANK").is_some() || var("WORLD_SIZE").is_some() {
            let rank = number("RANK")?.ok_or_else(|| bad("RANK", "WORLD_SIZE is set but RANK is not".to_string()))?;
            let world = number("WORLD_SIZE")?
                .ok_or_else(|| bad("WORLD_SIZE", "RANK is set but WORLD_SIZE is not".to_string()))?;
            let local = number("LOCAL_RANK")?.unwrap_or(0);
            let launcher = if var("TORCHELASTIC_RUN_ID").is_some() || var("TORCHELASTIC_USE_AGENT_STORE").is_some() {
                Launcher::Torchrun
            } else {
                Launcher::Env
            };
            (rank, world, local, launcher)
        } else if let Some(tasks) = number("SLURM_NTASKS")? {
            let rank = number("SLURM_PROCID")?
                .ok_or_else(|| bad("SLURM_PROCID", "SLURM_NTASKS is set but SLURM_PROCID is not".to_string()))?;
            let local = number("SLURM_LOCALID")?.unwrap_or(0);
            (rank, tasks, local, Launcher::Slurm)
        } else {
            return Ok(None);
        };
        if world_size == 0 {
            return Err(bad("WORLD_SIZE", "0 must be ≥ 1".to_string()));
        }
        if rank >= world_size {
            return Err(bad("RANK", format!("{rank} must be below the world size {world_size}")));
        }
        if let Some(local_world) = number("LOCAL_WORLD_SIZE")?
            && local_rank >= local_world
        {
            return Err(bad("LOCAL_RANK", format!("{local_rank} must be below LOCAL_WORLD_SIZE {local_world}")));
        }
        Ok(Some(Self { rank, world_size, local_rank, launcher }))
    }
}

/// The variable `name` from `var` as a non-negative integer, if set.
fn number(var: &impl Fn(&str) -> Option<String>, name: &str) -> Result<Option<usize>> {
    match var(name) {
        None => Ok(None),
        Some(text) => text.trim().parse::<usize>().map(Some).map_err(|_| Error::Launcher {
            variable: name.to_string(),
            reason: format!("`{text}` is not a non-negative integer"),
        }),
    }
}

/// The world size the launcher variables of this process give (`WORLD_SIZE`, else
/// `SLURM_NTASKS`), checked like a job's; `Ok(None)` without a launcher. Needs no rendezvous
/// address (the memory plan of a job is made before it is joined).
pub fn launcher_world_size() -> Result<Option<usize>> {
    Ok(Ranks::read(&|name: &str| std::env::var(name).ok())?.map(|ranks| ranks.world_size))
}

/// The first host of a Slurm host list: `node[03-05,9],gpu7` → `node03`.
pub fn first_host(list: &str) -> Option<String> {
    let list = list.trim();
    // The first entry ends at the first comma outside brackets.
    let mut depth = 0usize;
    let mut end = list.len();
    for (i, c) in list.char_indices() {
        match c {
            '[' => depth += 1,
            ']' => depth = depth.saturating_sub(1),
            ',' if depth == 0 => {
                end = i;
                break;
            }
            _ => {}
        }
    }
    let entry = &list[..end];
    let host = match entry.split_once('[') {
        None => entry.to_string(),
        Some((prefix, rest)) => {
            let range = rest.split([',', ']']).next()?;
            let first = range.split('-').next()?;
            format!("{prefix}{first}")
        }
    };
    (!host.is_empty()).then_some(host)
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use super::*;

    fn launch(vars: &[(&str, &str)]) -> Result<Option<Launch>> {
        let map: HashMap<String, String> = vars.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        Launch::from_vars(|name| map.get(name).cloned())
    }

    fn error(vars: &[(&str, &str)]) -> String {
        launch(vars).unwrap_err().to_string()
    }

    #[test]
    fn slurm_host_lists_give_their_first_host() {
        assert_eq!(first_host("node[03-05,9],gpu7").as_deref(), Some("node03"));
        assert_eq!(first_host("gpu7,node[1-2]").as_deref(), Some("gpu7"));
        assert_eq!(first_host("a-b-01").as_deref(), Some("a-b-01"));
        assert_eq!(first_host("n[7]").as_deref(), Some("n7"));
        assert_eq!(first_host(""), None);
    }

    #[test]
    fn launchers_are_read_from_their_variables() {
        assert_eq!(launch(&[]).unwrap(), None);
        assert_eq!(launch(&[("RANK", "0"), ("WORLD_SIZE", "1")]).unwrap(), None);
        let torchrun = launch(&[
            ("RANK", "1"),
            ("WORLD_SIZE", "2"),
            ("LOCAL_RANK", "1"),
            ("MASTER_ADDR", "127.0.0.1"),
            ("MASTER_PORT", "29400"),
            ("TORCHELASTIC_USE_AGENT_STORE", "True"),
            ("TORCHELASTIC_RESTART_COUNT", "2"),
        ])
        .unwrap()
        .unwrap();
        assert_eq!((torchrun.rank, torchrun.world_size, torchrun.local_rank), (1, 2, 1));
        assert_eq!(torchrun.launcher, Launcher::Torchrun);
        assert_eq!(torchrun.agent_store_prefix.as_deref(), Some("/worker/attempt_2"));
        let slurm = launch(&[
            ("SLURM_PROCID", "3"),
            ("SLURM_NTASKS", "4"),
            ("SLURM_LOCALID", "1"),
            ("SLURM_JOB_NODELIST", "gpu[12-13]"),
            ("SLURM_JOB_ID", "123456"),
        ])
        .unwrap()
        .unwrap();
        assert_eq!((slurm.rank, slurm.world_size, slurm.local_rank), (3, 4, 1));
        assert_eq!(slurm.master_addr, "gpu12");
        assert_eq!(slurm.master_port, SLURM_PORT_BASE + (123456 % SLURM_PORT_SPAN) as u16);
        assert_eq!(slurm.agent_store_prefix, None);
    }

    #[test]
    fn inconsistent_launcher_variables_are_named() {
        assert!(error(&[("RANK", "2"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "h")]).contains("RANK"));
        assert!(error(&[("RANK", "0"), ("WORLD_SIZE", "2")]).contains("MASTER_ADDR"));
        assert!(error(&[("RANK", "x"), ("WORLD_SIZE", "2")]).contains("`x`"));
        assert!(error(&[("WORLD_SIZE", "2")]).contains("RANK"));
        assert!(
            error(&[("RANK", "0"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "h"), ("MASTER_PORT", "70000")])
                .contains("MASTER_PORT")
        );
        assert!(error(&[("RANK", "0"), ("WORLD_SIZE", "0")]).contains("WORLD_SIZE"));
        assert!(error(&[("SLURM_PROCID", "0"), ("SLURM_NTASKS", "2")]).contains("MASTER_ADDR"));
        assert!(
            error(&[
                ("RANK", "0"),
                ("WORLD_SIZE", "2"),
                ("LOCAL_RANK", "3"),
                ("LOCAL_WORLD_SIZE", "2"),
                ("MASTER_ADDR", "h")
            ])
            .contains("LOCAL_RANK")
        );
    }
}
