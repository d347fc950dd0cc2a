//! Multi-process training on c10d/Gloo (CPU), launched by torchrun from the venv and by
//! RANK/WORLD_SIZE set by hand: 2 ranks × batch 1 equal 1 rank × batch 2, ZeRO-2 equals ZeRO-0
//! bit for bit, kill-and-relaunch resumes exactly, a dead or stalled rank fails the job naming
//! it, and ranks that disagree or bad launcher variables fail at start with nothing written.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use trainer::training::read_metrics;

use super::parity::{assert_success, python, read_tensors, repo_root};

/// The tiny config at global batch 2, with a `[distributed]` section.
pub(super) fn config(dir: &Path, name: &str, steps: u64, zero_stage: u8, lr: &str) -> PathBuf {
    let text = std::fs::read_to_string(repo_root().join("configs/pretrain_tiny.toml"))
        .unwrap()
        .replace("steps = 20", &format!("steps = {steps}"))
        .replace("batch_size = 1 ", "batch_size = 2 ")
        .replace("lr = 1e-3", &format!("lr = {lr}"))
        .replace("checkpoint_every = 10", "checkpoint_every = 2")
        .replace("keep_last = 2", "keep_last = 10")
        .replace("validate_every = 10", "validate_every = 3")
        .replace("validation_steps = 10", "validation_steps = 1");
    let text = format!("{text}\n[distributed]\nzero_stage = {zero_stage}\ntimeout_seconds = 20\nbucket_mib = 0.05\n");
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(&path, text).unwrap();
    path
}

pub(super) fn pretrain_args(config: &Path, shards: &Path, out: &Path, resume: bool) -> Vec<std::ffi::OsString> {
    let mut args: Vec<std::ffi::OsString> = vec!["pretrain".into(), "--config".into(), config.into()];
    args.extend(["--shards".into(), shards.into(), "--out".into(), out.into()]);
    if resume {
        args.push("--resume".into());
    }
    args
}

pub(super) fn torchrun(ranks: usize, args: &[std::ffi::OsString], port: u16) -> Command {
    let torchrun = python().with_file_name("torchrun");
    let mut cmd = Command::new(torchrun);
    cmd.args(["--nproc-per-node", &ranks.to_string(), "--master-port", &port.to_string(), "--no-python"])
        .arg(env!("CARGO_BIN_EXE_trainer"))
        .args(args);
    cmd
}

/// `ranks` processes with RANK/WORLD_SIZE set by hand (rank 0 hosts the store).
pub(super) fn by_hand(ranks: usize, args: impl Fn(usize) -> Vec<std::ffi::OsString>, port: u16) -> Vec<Child> {
    (0..ranks)
        .map(|rank| {
            Command::new(env!("CARGO_BIN_EXE_trainer"))
                .args(args(rank))
                .env("RANK", rank.to_string())
                .env("WORLD_SIZE", ranks.to_string())
                .env("MASTER_ADDR", "127.0.0.1")
                .env("MASTER_PORT", port.to_string())
                .env("OMP_NUM_THREADS", "1")
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect()
}

pub(super) fn losses(run: &Path) -> Vec<f64> {
    read_metrics(run).unwrap().iter().map(|m| m.loss).collect()
}

pub(super) fn weights(run: &Path, step: u64) -> std::collections::BTreeMap<String, trainer::tch::Tensor> {
    read_tensors(&run.join(format!("checkpoints/step-{step:08}/transformer/diffusion_pytorch_model.safetensors")))
}

/// Largest |a − b| over every weight of two checkpoints.
pub(super) fn max_weight_difference(a: &Path, b: &Path, step: u64) -> f64 {
    let (a, b) = (weights(a, step), weights(b, step));
    assert_eq!(a.len(), b.len());
    a.iter().map(|(name, t)| (t - &b[name]).abs().max().double_value(&[])).fold(0.0, f64::max)
}

pub(super) fn assert_losses_close(what: &str, actual: &[f64], expected: &[f64], relative: f64) {
    assert_eq!(actual.len(), expected.len(), "{what}: {actual:?} vs {expected:?}");
    for (step, (a, e)) in actual.iter().zip(expected).enumerate() {
        assert!((a - e).abs() <= relative * e.abs(), "{what}: step {} loss {a} vs {e}", step + 1);
    }
}

/// Tolerances. Losses: the ranks' transformer runs on batches of 1 where one process runs a
/// batch of 2, and sums come from Gloo instead of one process's mean, so values agree to fp32
/// reduction order: 1e-5 relative. Weights after 6 AdamW steps at lr 1e-4: a gradient
/// component that differs in its last bits moves its weight by at most ~lr per step through
/// AdamW's normalisation, so 6·lr bounds the difference; in practice it is far smaller.
pub(super) const LOSS_TOLERANCE: f64 = 1e-5;
pub(super) const LR: &str = "1e-4";
pub(super) const WEIGHT_TOLERANCE: f64 = 6.0 * 1e-4;

#[test]
fn two_ranks_equal_one_rank_and_zero2_equals_zero0_and_relaunch_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let steps = 6;
    let zero0 = config(dir.path(), "zero0", steps, 0, LR);
    let zero2 = config(dir.path(), "zero2", steps, 2, LR);

    let single = dir.path().join("single");
    assert_success(
        &Command::new(env!("CARGO_BIN_EXE_trainer"))
            .args(pretrain_args(&zero0, &shards, &single, false))
            .output()
            .unwrap(),
    );
    let ddp = dir.path().join("ddp");
    assert_success(&torchrun(2, &pretrain_args(&zero0, &shards, &ddp, false), 29531).output().unwrap());
    let sharded = dir.path().join("zero2");
    assert_success(&torchrun(2, &pretrain_args(&zero2, &shards, &sharded, false), 29532).output().unwrap());

    let reference = losses(&single);
    println!("1 rank x batch 2: {reference:?}\n2 ranks x batch 1: {:?}\nZeRO-2: {:?}", losses(&ddp), losses(&sharded));
    assert_losses_close("2 ranks vs 1 rank", &losses(&ddp), &reference, LOSS_TOLERANCE);
    let ddp_vs_single = max_weight_difference(&ddp, &single, steps);
    let zero_vs_ddp = max_weight_difference(&sharded, &ddp, steps);
    println!("max |weight| difference: 2 ranks vs 1 {ddp_vs_single:e}, ZeRO-2 vs ZeRO-0 {zero_vs_ddp:e}");
    assert!(ddp_vs_single <= WEIGHT_TOLERANCE);
    // The same sums (both all-reduce each bucket on Gloo) and the same element-wise update:
    // ZeRO-2 is ZeRO-0 bit for bit.
    assert_eq!(losses(&sharded), losses(&ddp), "ZeRO-2 vs ZeRO-0");
    assert_eq!(zero_vs_ddp, 0.0, "ZeRO-2 vs ZeRO-0 weights");
    // Only rank 0 wrote: one metrics line per step, one sample folder per validation, one event file.
    assert_eq!(read_metrics(&ddp).unwrap().len(), steps as usize);
    let events = std::fs::read_dir(&ddp)
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().starts_with("events.out.tfevents."));
    assert_eq!(events.count(), 1);
    assert!(ddp.join("samples/step-00000006/contact_sheet.png").is_file());
    // ZeRO-2 checkpoints hold one optimizer shard per rank.
    let step2 = sharded.join("checkpoints/step-00000002");
    assert!(step2.join("optimizer-rank-00000-of-00002.safetensors").is_file());
    assert!(step2.join("optimizer-rank-00001-of-00002.safetensors").is_file());
    assert!(!step2.join("optimizer.safetensors").exists());
    // Every file of the checkpoints written at 1 and 2 ranks, ZeRO-0 and ZeRO-2, is verified.
    for run in [&single, &ddp, &sharded] {
        super::long_runs::assert_each_damage_is_caught(run);
    }

    // Killed after its step-4 checkpoint, relaunched: the uninterrupted run exactly.
    let killed = dir.path().join("killed");
    let mut job = torchrun(2, &pretrain_args(&zero2, &shards, &killed, false), 29533)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let marker = killed.join("checkpoints/step-00000004/state.json");
    let deadline = Instant::now() + Duration::from_secs(300);
    while !marker.is_file() {
        assert!(Instant::now() < deadline && job.try_wait().unwrap().is_none(), "the job ended before step 4");
        std::thread::sleep(Duration::from_millis(100));
    }
    // SIGKILL to the agent and its workers at once (each worker runs in a session of its own).
    let mut tree = descendants(job.id());
    tree.push(job.id());
    signal("KILL", &tree);
    let _ = job.wait();
    // The workers may outlive the agent for an instant.
    std::thread::sleep(Duration::from_secs(1));
    let copy = dir.path().join("killed-copy");
    copy_tree(&killed, &copy);
    // Its newest checkpoint damaged in rank 1's optimizer shard: the 2 ranks, which share the
    // check of the files, skip it and continue from the one before to the same end.
    let newest = trainer::training::list_checkpoints(&killed).last().unwrap().1.clone();
    let shard = newest.join("optimizer-rank-00001-of-00002.safetensors");
    std::fs::OpenOptions::new().write(true).open(&shard).unwrap().set_len(100).unwrap();
    let relaunched = torchrun(2, &pretrain_args(&zero2, &shards, &killed, true), 29534).output().unwrap();
    assert_success(&relaunched);
    let err = String::from_utf8_lossy(&relaunched.stderr);
    let skipped = format!(
        "skipping checkpoint {}: optimizer-rank-00001-of-00002.safetensors",
        newest.file_name().unwrap().to_string_lossy()
    );
    assert!(err.contains(&skipped), "{err}");
    assert_eq!(losses(&killed), losses(&sharded), "relaunched 2-rank run must repeat the uninterrupted one");
    assert_eq!(max_weight_difference(&killed, &sharded, steps), 0.0);

    // The same ZeRO-2 checkpoint resumed by one process (per-rank shards into one AdamW).
    assert_success(
        &Command::new(env!("CARGO_BIN_EXE_trainer"))
            .args(pretrain_args(&zero0, &shards, &copy, true))
            .output()
            .unwrap(),
    );
    assert_losses_close("1 rank resuming a 2-rank checkpoint", &losses(&copy), &losses(&sharded), LOSS_TOLERANCE);
    assert!(max_weight_difference(&copy, &sharded, steps) <= WEIGHT_TOLERANCE);
}

/// The processes below `pid`, children before their own children, read from `/proc`.
fn descendants(pid: u32) -> Vec<u32> {
    let mut found = Vec::new();
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else { return found };
    for task in tasks.flatten() {
        let children = std::fs::read_to_string(task.path().join("children")).unwrap_or_default();
        for child in children.split_whitespace().map(|c| c.parse::<u32>().unwrap()) {
            found.push(child);
            found.extend(descendants(child));
        }
    }
    found
}

/// Sends SIG`name` to each of `pids`, one positive process id at a time. Never a process group:
/// Debian 12's procps `kill` misreads `-PGID` (`kill -0 -20108` makes the call `kill(-2, 0)`), and
/// a group id starting with 1 becomes `kill(-1, …)`, every process the caller may signal.
pub(super) fn signal(name: &str, pids: &[u32]) {
    for &pid in pids {
        assert!(pid > 1, "refusing to signal process {pid}");
        let _ = Command::new("kill").args([format!("-{name}"), pid.to_string()]).status().unwrap();
    }
}

pub(super) fn copy_tree(from: &Path, to: &Path) {
    let status = Command::new("cp").arg("-a").arg(from).arg(to).status().unwrap();
    assert!(status.success());
}

/// Waits for `child` at most `limit`; kills it and fails when it is still running.
pub(super) fn wait_within(child: &mut Child, limit: Duration) -> (std::process::ExitStatus, String, Duration) {
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let mut stderr = String::new();
            use std::io::Read;
            child.stderr.take().unwrap().read_to_string(&mut stderr).unwrap();
            return (status, stderr, started.elapsed());
        }
        if started.elapsed() > limit {
            let _ = child.kill();
            panic!("still running after {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn a_dead_or_stalled_rank_fails_the_others_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let config = config(dir.path(), "long", 10_000, 0, LR);
    for (signal_name, port, words) in [("KILL", 29541, "rank 1"), ("STOP", 29542, "no heartbeat")] {
        let out = dir.path().join(format!("run-{signal_name}"));
        let mut ranks = by_hand(2, |_| pretrain_args(&config, &shards, &out, false), port);
        let metrics = out.join("metrics.jsonl");
        let deadline = Instant::now() + Duration::from_secs(300);
        while std::fs::read_to_string(&metrics).map_or(0, |t| t.lines().count()) < 2 {
            assert!(Instant::now() < deadline, "no progress");
            std::thread::sleep(Duration::from_millis(100));
        }
        signal(signal_name, &[ranks[1].id()]);
        // The timeout is 20 s; a dead peer is noticed at once, a stalled one within the timeout.
        let (status, stderr, took) = wait_within(&mut ranks[0], Duration::from_secs(60));
        println!("after SIG{signal_name} of rank 1, rank 0 exited in {took:.1?}:\n{stderr}");
        assert!(!status.success());
        assert!(stderr.contains(words) && stderr.contains("collective"), "{stderr}");
        let _ = ranks[1].kill();
        let _ = ranks[1].wait();
    }
}

#[test]
fn ranks_that_disagree_or_bad_launcher_variables_fail_at_start_writing_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let a = config(dir.path(), "a", 2, 0, LR);
    let b = config(dir.path(), "b", 2, 0, "2e-4");
    let out = dir.path().join("disagree");
    let mut ranks = by_hand(2, |rank| pretrain_args(if rank == 0 { &a } else { &b }, &shards, &out, false), 29551);
    for rank in &mut ranks {
        let (status, stderr, _) = wait_within(rank, Duration::from_secs(120));
        assert!(!status.success() && stderr.contains("disagree") && stderr.contains("training config"), "{stderr}");
    }
    assert!(!out.exists(), "nothing may be written");

    // The rendezvous gives up after the config's timeout: 2 s here, so that the unreachable
    // store below fails fast (the other runs fail before any rendezvous).
    let short = dir.path().join("short.toml");
    let text = std::fs::read_to_string(&a).unwrap().replace("timeout_seconds = 20", "timeout_seconds = 2");
    std::fs::write(&short, text).unwrap();
    let run = |vars: &[(&str, &str)]| -> String {
        let out = dir.path().join("bad");
        let output = Command::new(env!("CARGO_BIN_EXE_trainer"))
            .args(pretrain_args(&short, &shards, &out, false))
            .envs(vars.iter().copied())
            .output()
            .unwrap();
        assert!(!output.status.success());
        assert!(!out.exists(), "nothing may be written for {vars:?}");
        String::from_utf8_lossy(&output.stderr).into_owned()
    };
    assert!(run(&[("RANK", "2"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "127.0.0.1")]).contains("RANK"));
    assert!(run(&[("RANK", "0"), ("WORLD_SIZE", "2")]).contains("MASTER_ADDR"));
    // Nobody listens on the master port: the client gives up within the timeout, naming it.
    let unreachable =
        run(&[("RANK", "1"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "127.0.0.1"), ("MASTER_PORT", "29559")]);
    assert!(
        unreachable.contains("could not reach")
            && unreachable.contains("127.0.0.1:29559")
            && unreachable.contains("2 s"),
        "{unreachable}"
    );
    // The port is taken: rank 0 cannot host the store.
    let taken = std::net::TcpListener::bind("0.0.0.0:0").unwrap();
    let port = taken.local_addr().unwrap().port().to_string();
    let in_use = run(&[("RANK", "0"), ("WORLD_SIZE", "2"), ("MASTER_ADDR", "127.0.0.1"), ("MASTER_PORT", &port)]);
    assert!(in_use.contains("could not host") && in_use.contains(&port), "{in_use}");
}

#[test]
fn finetune_on_two_ranks_equals_one_and_logs_tensorboard_events() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let zero0 = config(dir.path(), "zero0", 2, 0, LR);
    let base = dir.path().join("base");
    assert_success(
        &Command::new(env!("CARGO_BIN_EXE_trainer"))
            .args(pretrain_args(&zero0, &shards, &base, false))
            .output()
            .unwrap(),
    );
    let init = base.join("checkpoints/step-00000002");
    // Finetuning cuts the test video into clips of 9 frames: 27 frames give 3, one per rank and more.
    let video = dir.path().join("video");
    let scene = datagen::synth::SynthConfig { width: 96, height: 64, frames: 27, seed: 5, ..Default::default() };
    datagen::synth::write_sequence(&scene, &video, |_| {}).unwrap();
    let finetune = |out: &Path| -> Vec<std::ffi::OsString> {
        let mut args: Vec<std::ffi::OsString> = vec!["finetune".into(), "--init".into(), init.clone().into()];
        args.extend(["--sequence".into(), video.clone().into(), "--out".into(), out.into()]);
        args.extend(["--steps".into(), "3".into(), "--trajectories".into(), "2".into()]);
        args
    };
    let single = dir.path().join("ft-single");
    assert_success(&Command::new(env!("CARGO_BIN_EXE_trainer")).args(finetune(&single)).output().unwrap());
    let ranks = dir.path().join("ft-ranks");
    assert_success(&torchrun(2, &finetune(&ranks), 29561).output().unwrap());
    assert_losses_close("finetune on 2 ranks vs 1", &losses(&ranks), &losses(&single), LOSS_TOLERANCE);
    assert!(max_weight_difference(&ranks, &single, 3) <= WEIGHT_TOLERANCE);

    // The run's event file, read by tensorboard's own reader: one scalar per step for each tag,
    // equal to metrics.jsonl, and the validation contact sheet (validate_every = 3).
    let read = read_events(&ranks, dir.path());
    let metrics = read_metrics(&ranks).unwrap();
    let series = read["scalars"]["train/loss"].as_array().unwrap();
    assert_eq!(series.len(), metrics.len());
    for (event, m) in series.iter().zip(&metrics) {
        assert_eq!(event[0].as_u64().unwrap(), m.step);
        assert_eq!(event[1].as_f64().unwrap() as f32, m.loss as f32);
    }
    for tag in ["train/lr", "train/grad_norm", "train/step_seconds", "train/samples_per_second"] {
        assert_eq!(read["scalars"][tag].as_array().unwrap().len(), metrics.len(), "{tag}");
    }
    assert_eq!(read["images"]["validation/contact_sheet"].as_array().unwrap().len(), 1, "{read}");
}

/// What tensorboard's own reader finds in the event files of `run` (`scripts/read_tensorboard.py`:
/// scalars and images by tag), with `scratch` for its input folder and output.
pub(super) fn read_events(run: &Path, scratch: &Path) -> serde_json::Value {
    let events = scratch.join("events");
    std::fs::create_dir_all(&events).unwrap();
    for entry in std::fs::read_dir(run).unwrap() {
        let path = entry.unwrap().path();
        if path.file_name().unwrap().to_string_lossy().starts_with("events.out.tfevents.") {
            std::fs::copy(&path, events.join(path.file_name().unwrap())).unwrap();
        }
    }
    let out = scratch.join("events.json");
    super::parity::run_python("read_tensorboard.py", &[events.as_os_str(), out.as_os_str()]);
    serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap()
}
