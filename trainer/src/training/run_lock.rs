//! One writer per run folder: `RUN/trainer.lock`, an exclusive OS advisory lock (`flock`) that
//! rank 0 takes before it writes anything into the folder and holds for the whole run. A second
//! run on the folder (a relaunched job while the old one is still being torn down, the same
//! command typed twice) refuses at once, naming the holder's host and pid; the other ranks of the
//! holder's own job never take it. The OS drops the lock when the holding process ends, however it
//! ends, so a crashed or killed run leaves nothing stale behind. On a shared filesystem the lock
//! holds across nodes where the filesystem supports `flock` (NFSv4, Lustre mounted with `flock`).

use std::fs::{File, OpenOptions, TryLockError};
use std::io::Write;
use std::path::{Path, PathBuf};

use super::consensus;
use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};

/// File name of the lock in a run folder.
pub const LOCK_NAME: &str = "trainer.lock";

/// The lock of a run folder, held until dropped (on ranks other than 0: nothing is held).
#[derive(Debug)]
pub struct RunLock {
    file: Option<File>,
    path: PathBuf,
}

impl RunLock {
    /// Takes the lock of `run` for `command` (`trainer pretrain`), creating the folder, or fails
    /// at once naming the process that holds it.
    pub fn acquire(run: &Path, command: &str) -> Result<Self> {
        std::fs::create_dir_all(run).map_err(|error| Error::Io { path: run.to_path_buf(), error })?;
        let path = run.join(LOCK_NAME);
        let io = |error| Error::Io { path: path.clone(), error };
        let file = OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => return Err(busy(run, &path)),
            Err(TryLockError::Error(error)) => return Err(io(error)),
        }
        // Who holds it, for the message a second run prints.
        let mut writer = &file;
        writer.set_len(0).and_then(|()| writer.write_all(holder_line(command).as_bytes())).map_err(io)?;
        Ok(Self { file: Some(file), path })
    }

    /// [`Self::acquire`] as one rank of `pg`: rank 0 takes the lock and every rank learns whether
    /// it did (one collective), so a refused job stops on every rank with nothing written.
    pub fn acquire_on(run: &Path, command: &str, pg: Option<&ProcessGroup>) -> Result<Self> {
        let rank = pg.map_or(0, |pg| pg.rank);
        let taken = if rank == 0 { Some(Self::acquire(run, command)) } else { None };
        let [refused] = consensus::any_rank(pg, [matches!(taken, Some(Err(_)))], "run lock")?;
        match taken {
            Some(result) => result,
            None if refused => Err(Error::InvalidArgument {
                name: "out".to_string(),
                reason: format!("rank 0 could not take the lock of {} (its message says why)", run.display()),
            }),
            None => Ok(Self { file: None, path: run.join(LOCK_NAME) }),
        }
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether this process holds the lock (rank 0), rather than belonging to the holder's job.
    pub fn is_held(&self) -> bool {
        self.file.is_some()
    }
}

/// `host H pid P: COMMAND [, Slurm job J]`: who holds a lock.
fn holder_line(command: &str) -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .ok()
        .filter(|h| !h.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "unknown".to_string());
    let job = std::env::var("SLURM_JOB_ID").map(|id| format!(", Slurm job {id}")).unwrap_or_default();
    format!("host {host} pid {} ({command}{job})\n", std::process::id())
}

fn busy(run: &Path, lock: &Path) -> Error {
    let holder = std::fs::read_to_string(lock).ok().map(|t| t.trim().to_string()).filter(|t| !t.is_empty());
    let holder = holder.unwrap_or_else(|| "a process that is still starting".to_string());
    Error::InvalidArgument {
        name: "out".to_string(),
        reason: format!(
            "{} is in use by another training run ({}: {holder}); wait for it to end (a run that \
             crashed or was killed releases the lock by itself) or choose another folder",
            run.display(),
            lock.display()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_naming_the_first_until_it_lets_go() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("run");
        let first = RunLock::acquire(&run, "trainer pretrain").unwrap();
        assert!(first.is_held());
        // flock locks belong to an open file: a second open, even in this process, is refused.
        let refused = RunLock::acquire(&run, "trainer finetune").unwrap_err().to_string();
        let pid = format!("pid {}", std::process::id());
        assert!(
            refused.contains(&pid) && refused.contains("host ") && refused.contains("trainer pretrain"),
            "{refused}"
        );
        drop(first);
        let second = RunLock::acquire(&run, "trainer finetune").unwrap();
        let holder = std::fs::read_to_string(second.path()).unwrap();
        assert!(holder.contains("trainer finetune") && !holder.contains("trainer pretrain"), "{holder}");
    }
}
