//! Long runs on the CPU with the tiny preset: a preempted run (SIGTERM at 1 rank, SIGUSR1 to one
//! of 2 ranks, `finetune`) checkpoints its step and resumes to the uninterrupted run; a second
//! signal or the grace deadline stops at once; one writer per run folder (live holder, dead
//! holder, the ranks of one job); damaged checkpoints are skipped and never outlive the last
//! intact one; a full disk stops the run with its earlier checkpoints intact; checkpoints every
//! few minutes.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use trainer::training::{checkpoint, list_checkpoints, read_metrics};

use super::distributed::{
    LOSS_TOLERANCE, LR, WEIGHT_TOLERANCE, assert_losses_close, by_hand, config, copy_tree, losses,
    max_weight_difference, pretrain_args, signal, wait_within,
};
use super::parity::assert_success;

/// The distributed tests' tiny config (global batch 2, lr 1e-4) without validation samples,
/// with `[loop]` lines replaced or added.
fn long_config(dir: &Path, name: &str, steps: u64, zero_stage: u8, settings: &[(&str, &str)]) -> PathBuf {
    let path = config(dir, name, steps, zero_stage, LR);
    let mut text = std::fs::read_to_string(&path).unwrap().replace("validate_every = 3", "validate_every = 0");
    for (key, value) in settings {
        let line = text.lines().find(|l| l.starts_with(&format!("{key} = "))).map(str::to_string);
        text = match line {
            Some(line) => text.replace(&line, &format!("{key} = {value}")),
            None => text.replace("[loop]", &format!("[loop]\n{key} = {value}")),
        };
    }
    std::fs::write(&path, text).unwrap();
    path
}

fn trainer(args: &[std::ffi::OsString]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.args(args).env("RUST_BACKTRACE", "0").env("OMP_NUM_THREADS", "1");
    cmd
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// Waits until `run` has logged `lines` steps.
fn wait_for_steps(run: &Path, lines: usize) {
    let deadline = Instant::now() + Duration::from_secs(300);
    while std::fs::read_to_string(run.join("metrics.jsonl")).map_or(0, |t| t.lines().count()) < lines {
        assert!(Instant::now() < deadline, "{} logged fewer than {lines} steps", run.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn newest_step(run: &Path) -> u64 {
    list_checkpoints(run).last().map_or(0, |(step, _)| *step)
}

#[test]
fn a_preempted_run_checkpoints_its_step_and_resumes_to_the_uninterrupted_run() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let steps = 40;
    // Off-schedule checkpoints only: the preemption's own.
    let settings = [("checkpoint_every", "1000")];
    let zero0 = long_config(dir.path(), "zero0", steps, 0, &settings);
    let zero2 = long_config(dir.path(), "zero2", steps, 2, &settings);
    let reference = dir.path().join("reference");
    assert_success(&trainer(&pretrain_args(&zero0, &shards, &reference, false)).output().unwrap());

    // One process, SIGTERM: exit 75 after a checkpoint of the step it was in.
    let run = dir.path().join("one");
    let mut job = trainer(&pretrain_args(&zero0, &shards, &run, false))
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_for_steps(&run, 3);
    signal("TERM", &[job.id()]);
    let (status, err, _) = wait_within(&mut job, Duration::from_secs(120));
    assert_eq!(status.code(), Some(75), "{err}");
    let done = read_metrics(&run).unwrap().len() as u64;
    assert!(done < steps, "the signal came after the last step: {err}");
    assert_eq!(newest_step(&run), done, "the checkpoint is the last step's: {err}");
    assert!(err.contains("SIGTERM") && err.contains("--resume"), "{err}");
    assert_success(&trainer(&pretrain_args(&zero0, &shards, &run, true)).output().unwrap());
    assert_eq!(losses(&run), losses(&reference), "the resumed run repeats the uninterrupted losses exactly");
    assert_eq!(max_weight_difference(&run, &reference, steps), 0.0);

    // Two ranks (ZeRO-2), SIGUSR1 to rank 1 only: both finish the same step, one complete
    // checkpoint, both exit 75; the relaunch ends where one rank at the same global batch does.
    let ranks = dir.path().join("two");
    let mut job = by_hand(2, |_| pretrain_args(&zero2, &shards, &ranks, false), 29571);
    wait_for_steps(&ranks, 3);
    signal("USR1", &[job[1].id()]);
    for rank in &mut job {
        let (status, err, _) = wait_within(rank, Duration::from_secs(120));
        assert_eq!(status.code(), Some(75), "{err}");
    }
    let done = read_metrics(&ranks).unwrap().len() as u64;
    assert!(done < steps);
    assert_eq!(newest_step(&ranks), done);
    for rank in 0..2 {
        let shard = format!("checkpoints/step-{done:08}/optimizer-rank-{rank:05}-of-00002.safetensors");
        assert!(ranks.join(&shard).is_file(), "{shard}");
    }
    for rank in &mut by_hand(2, |_| pretrain_args(&zero2, &shards, &ranks, true), 29572) {
        let (status, err, _) = wait_within(rank, Duration::from_secs(300));
        assert!(status.success(), "{err}");
    }
    assert_losses_close("preempted 2-rank run vs 1 rank", &losses(&ranks), &losses(&reference), LOSS_TOLERANCE);
    assert!(max_weight_difference(&ranks, &reference, steps) <= WEIGHT_TOLERANCE);
}

#[test]
fn a_second_signal_or_the_grace_deadline_stops_at_once_without_a_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    // Rank 1 stopped (SIGSTOP) keeps rank 0 waiting in a collective after its signal, so only
    // the second signal or the deadline can end it: a straggler that never reaches the checkpoint.
    for (case, grace, port) in [("second signal", "0", 29573), ("deadline", "1", 29574)] {
        let settings = [("checkpoint_every", "1000"), ("preempt_grace_seconds", grace)];
        let config = long_config(dir.path(), &format!("grace-{grace}"), 10_000, 0, &settings);
        let run = dir.path().join(case.replace(' ', "-"));
        let mut ranks = by_hand(2, |_| pretrain_args(&config, &shards, &run, false), port);
        wait_for_steps(&run, 2);
        signal("STOP", &[ranks[1].id()]);
        signal("TERM", &[ranks[0].id()]);
        if case == "second signal" {
            std::thread::sleep(Duration::from_millis(200));
            signal("TERM", &[ranks[0].id()]);
        }
        // The collectives' timeout is 20 s: an exit through it would be status 1.
        let (status, err, took) = wait_within(&mut ranks[0], Duration::from_secs(60));
        println!("{case}: rank 0 exited in {took:.1?} with {status}");
        assert_eq!(status.code(), Some(128 + 15), "{case}: {err}");
        if case == "deadline" {
            assert!(err.contains("grace period of 1 s"), "{err}");
        }
        assert!(list_checkpoints(&run).is_empty(), "{case}: no checkpoint may be marked complete");
        signal("KILL", &[ranks[1].id()]);
        let _ = ranks[1].wait();
    }
}

#[test]
fn finetune_is_preempted_and_resumed_to_the_uninterrupted_finetune() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let base = dir.path().join("base");
    let config = long_config(dir.path(), "base", 2, 0, &[]);
    assert_success(&trainer(&pretrain_args(&config, &shards, &base, false)).output().unwrap());
    let video = dir.path().join("video");
    let scene = datagen::synth::SynthConfig { width: 96, height: 64, frames: 18, seed: 5, ..Default::default() };
    datagen::synth::write_sequence(&scene, &video, |_| {}).unwrap();
    let steps = 30;
    let finetune = |out: &Path, resume: bool| -> Command {
        let mut args: Vec<std::ffi::OsString> =
            vec!["finetune".into(), "--init".into(), base.join("checkpoints/step-00000002").into()];
        args.extend(["--sequence".into(), video.clone().into(), "--out".into(), out.into()]);
        args.extend(["--steps".into(), steps.to_string().into(), "--trajectories".into(), "1".into()]);
        if resume {
            args.push("--resume".into());
        }
        trainer(&args)
    };
    let reference = dir.path().join("ft-reference");
    assert_success(&finetune(&reference, false).output().unwrap());
    let run = dir.path().join("ft");
    let mut job = finetune(&run, false).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    wait_for_steps(&run, 3);
    signal("TERM", &[job.id()]);
    let (status, err, _) = wait_within(&mut job, Duration::from_secs(120));
    assert_eq!(status.code(), Some(75), "{err}");
    let done = read_metrics(&run).unwrap().len() as u64;
    assert!(done < steps && newest_step(&run) == done, "{err}");
    assert_success(&finetune(&run, true).output().unwrap());
    assert_eq!(losses(&run), losses(&reference));
    assert_eq!(max_weight_difference(&run, &reference, steps), 0.0);
}

#[test]
fn one_writer_per_run_folder_live_holder_dead_holder_and_the_ranks_of_one_job() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let config = long_config(dir.path(), "long", 10_000, 0, &[("checkpoint_every", "2")]);
    let run = dir.path().join("run");
    // The holder: a 2-rank job (rank 0 holds the lock, rank 1 runs beside it).
    let mut holder = by_hand(2, |_| pretrain_args(&config, &shards, &run, false), 29575);
    wait_for_steps(&run, 3);
    let holder_pid = format!("pid {}", holder[0].id());
    let config_before = std::fs::read(run.join("config.json")).unwrap();

    // A second process, and a second 2-rank job, are refused at once, naming the holder.
    let second = trainer(&pretrain_args(&config, &shards, &run, true)).output().unwrap();
    let err = stderr(&second);
    assert!(!second.status.success() && err.contains("in use by another training run"), "{err}");
    assert!(err.contains(&holder_pid) && err.contains("host "), "{err}");
    let mut job = by_hand(2, |_| pretrain_args(&config, &shards, &run, true), 29576);
    let (status0, err0, _) = wait_within(&mut job[0], Duration::from_secs(60));
    let (status1, err1, _) = wait_within(&mut job[1], Duration::from_secs(60));
    assert!(!status0.success() && err0.contains(&holder_pid), "{err0}");
    assert!(!status1.success() && err1.contains("rank 0 could not take the lock"), "{err1}");
    assert_eq!(std::fs::read(run.join("config.json")).unwrap(), config_before, "the refused job wrote nothing");
    let events = std::fs::read_dir(&run)
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().starts_with("events."));
    assert_eq!(events.count(), 1, "only the holder logs");

    // The holder dies (SIGKILL: no chance to clean up): its lock goes with it.
    signal("KILL", &[holder[0].id(), holder[1].id()]);
    for rank in &mut holder {
        let _ = rank.wait();
    }
    let target = newest_step(&run) + 1;
    let resumed =
        trainer(&pretrain_args(&config, &shards, &run, true)).arg("--steps").arg(target.to_string()).output().unwrap();
    assert_success(&resumed);
    assert_eq!(newest_step(&run), target);
}

/// Damages one file of a checkpoint: truncated, deleted, or one byte in its middle changed.
fn damage(path: &Path, how: &str) {
    match how {
        "truncated" => {
            let len = std::fs::metadata(path).unwrap().len();
            std::fs::OpenOptions::new().write(true).open(path).unwrap().set_len(len / 2).unwrap();
        }
        "deleted" => std::fs::remove_file(path).unwrap(),
        "altered" => {
            let mut bytes = std::fs::read(path).unwrap();
            let middle = bytes.len() / 2;
            bytes[middle] ^= 0x55;
            std::fs::write(path, bytes).unwrap();
        }
        other => panic!("unknown damage {other}"),
    }
}

/// Every file of the newest checkpoint of `run` (its `state.json` included), truncated, deleted
/// and altered in turn on a copy of the run: the check finds the file, and resuming would take
/// the checkpoint before it.
pub(super) fn assert_each_damage_is_caught(run: &Path) {
    let all = list_checkpoints(run);
    let [.., (older, _), (newest, _)] = all.as_slice() else { panic!("{}: two checkpoints needed", run.display()) };
    let newest_dir = format!("checkpoints/step-{newest:08}");
    let state = checkpoint::read_state(&run.join(&newest_dir)).unwrap();
    let mut names: Vec<String> = state.files.keys().cloned().collect();
    assert!(names.iter().any(|n| n.contains("optimizer")) && names.iter().any(|n| n.starts_with("transformer/")));
    names.push(checkpoint::STATE_NAME.to_string());
    let copy = run.with_extension("damaged");
    for name in &names {
        for how in ["truncated", "deleted", "altered"] {
            let _ = std::fs::remove_dir_all(&copy);
            copy_tree(run, &copy);
            damage(&copy.join(&newest_dir).join(name), how);
            let (dir, _) = checkpoint::newest_intact(&copy, None).unwrap().expect("an older intact checkpoint");
            assert!(dir.ends_with(format!("step-{older:08}")), "{name} {how}: resumed from {}", dir.display());
            let chosen = checkpoint::read_state(&copy.join(&newest_dir));
            if name != checkpoint::STATE_NAME
                && let Ok(state) = chosen
            {
                let problems = checkpoint::check_files(&copy.join(&newest_dir), &state, true, (0, 1));
                assert!(
                    problems.len() == 1 && problems[0].starts_with(&format!("{name}: ")),
                    "{name} {how}: {problems:?}"
                );
            }
        }
    }
    let _ = std::fs::remove_dir_all(&copy);
}

#[test]
fn a_damaged_newest_checkpoint_is_skipped_and_never_outlives_the_last_intact_one() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let first = long_config(dir.path(), "first", 4, 0, &[]);
    let run = dir.path().join("run");
    assert_success(&trainer(&pretrain_args(&first, &shards, &run, false)).output().unwrap());
    assert_each_damage_is_caught(&run);

    // step-4 damaged; resumed with keep_last = 2 and a checkpoint every step up to 3: the run
    // continues from step 2, and the two intact checkpoints 2 and 3 are kept (counting the
    // damaged step 4 as one of two would remove step 2).
    damage(&run.join("checkpoints/step-00000004/transformer/diffusion_pytorch_model.safetensors"), "truncated");
    let resumed = long_config(dir.path(), "resumed", 3, 0, &[("checkpoint_every", "1"), ("keep_last", "2")]);
    let output = trainer(&pretrain_args(&resumed, &shards, &run, true)).output().unwrap();
    assert_success(&output);
    let err = stderr(&output);
    assert!(
        err.contains("skipping checkpoint step-00000004: transformer/diffusion_pytorch_model.safetensors"),
        "{err}"
    );
    assert!(err.contains("continuing from step-00000002"), "{err}");
    let kept: Vec<u64> = list_checkpoints(&run).into_iter().map(|(s, _)| s).collect();
    assert_eq!(kept, vec![2, 3, 4], "the intact 2 and 3, and the damaged 4 the run will rewrite");
    assert_eq!(checkpoint::newest_intact(&run, None).unwrap().unwrap().1.step, 3);
}

/// Root mounts a tmpfs of `bytes` at `dir` for the life of the guard.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, bytes: u64) -> Self {
        std::fs::create_dir_all(dir).unwrap();
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(dir)
            .status()
            .unwrap();
        assert!(status.success(), "mount -t tmpfs at {} failed: {status}", dir.display());
        Self(dir.to_path_buf())
    }

    fn resize(&self, bytes: u64) {
        let status =
            Command::new("mount").args(["-o", &format!("remount,size={bytes}")]).arg(&self.0).status().unwrap();
        assert!(status.success());
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

fn is_root() -> bool {
    Command::new("id").arg("-u").output().is_ok_and(|o| o.stdout.starts_with(b"0\n"))
}

#[test]
fn a_full_disk_stops_the_run_cleanly_with_its_earlier_checkpoints_intact() {
    if !is_root() {
        println!("skipped: mounting the small filesystem needs root (CI runs as root)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let settings = [("checkpoint_every", "1"), ("keep_last", "1")];
    for (ranks, zero_stage, port) in [(1, 0, 0), (2, 2, 29577)] {
        let config = long_config(dir.path(), &format!("zero{zero_stage}"), 4, zero_stage, &settings);
        let reference = dir.path().join(format!("reference-{ranks}"));
        let run = dir.path().join(format!("full-{ranks}"));
        let launch = |out: &Path, resume: bool| -> Vec<(std::process::ExitStatus, String)> {
            if ranks == 1 {
                let output = trainer(&pretrain_args(&config, &shards, out, resume)).output().unwrap();
                vec![(output.status, stderr(&output))]
            } else {
                let mut job = by_hand(ranks, |_| pretrain_args(&config, &shards, out, resume), port);
                job.iter_mut()
                    .map(|rank| {
                        let (s, e, _) = wait_within(rank, Duration::from_secs(300));
                        (s, e)
                    })
                    .collect()
            }
        };
        for (status, err) in launch(&reference, false) {
            assert!(status.success(), "{err}");
        }
        // Room for one checkpoint and a half: the second (written before the first goes) fails.
        let size: u64 = checkpoint::read_state(&reference.join("checkpoints/step-00000004"))
            .unwrap()
            .files
            .values()
            .map(|f| f.bytes)
            .sum();
        let disk = Tmpfs::mount(&run.join("checkpoints"), size * 3 / 2);
        for (status, err) in launch(&run, false) {
            assert_eq!(status.code(), Some(74), "{err}");
            assert!(
                err.contains("checkpoint of step 2 could not be written") && err.contains("No space left"),
                "{err}"
            );
            assert!(err.contains("earlier checkpoints are untouched") && err.contains("step-00000001"), "{err}");
        }
        assert_eq!(read_metrics(&run).unwrap().len(), 2, "no step after the failed checkpoint");
        let names: Vec<String> = std::fs::read_dir(run.join("checkpoints"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, vec!["step-00000001"], "the partial checkpoint is gone");
        let (dir1, state) = checkpoint::newest_intact(&run, None).unwrap().unwrap();
        assert_eq!(state.step, 1, "{}", dir1.display());
        // With room again, --resume finishes the run as if nothing happened.
        disk.resize(size * 4);
        for (status, err) in launch(&run, true) {
            assert!(status.success(), "{err}");
        }
        assert_eq!(losses(&run), losses(&reference));
        drop(disk);
    }
}

#[test]
fn checkpoints_every_few_minutes() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    // A step takes far longer than 6 ms: a checkpoint after every one; in an hour: the last only.
    for (every, expected) in [("\"0.0001min\"", vec![1, 2, 3]), ("\"60 min\"", vec![3])] {
        let config = long_config(dir.path(), "timed", 3, 0, &[("checkpoint_every", every)]);
        let run = dir.path().join(format!("every-{}", expected.len()));
        assert_success(&trainer(&pretrain_args(&config, &shards, &run, false)).output().unwrap());
        let steps: Vec<u64> = list_checkpoints(&run).into_iter().map(|(s, _)| s).collect();
        assert_eq!(steps, expected, "checkpoint_every = {every}");
    }
}
