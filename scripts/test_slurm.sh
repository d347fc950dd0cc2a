#!/usr/bin/env bash
# A real Slurm on this machine: starts munged, slurmctld and slurmd for a one-node cluster on
# loopback (private munge key, slurm.conf, state and spool folders, all in one temp folder), then
#   (a) runs scripts/build_corpus.sbatch as a 2-task job array over a small synthetic corpus and
#       checks that the result equals a one-worker `datagen build` (same clips, same BLAKE3 of
#       every encoded frame and co-visibility mask, as datagen's corpus tests compare them);
#   (b) runs a 2-task `srun` of `trainer pretrain` on configs/pretrain_tiny.toml (few steps) and
#       checks that both tasks exit 0 and that exactly one run folder with checkpoints exists;
#       then submits the same training as scripts/train.sbatch, sends its tasks SIGUSR1 mid-run
#       (what the script's `--signal` asks Slurm to send ahead of the time limit), and checks
#       that the trainer checkpointed and exited 75, that the script requeued the job, and that
#       the requeued job resumed and finished with losses and weights equal to the srun's.
# Every daemon it started is stopped on exit, and the temp folder removed (KEEP=1 keeps it).
#
#   cargo build -p datagen -p trainer --bins
#   bash scripts/test_slurm.sh          # (a) and (b)
#   bash scripts/test_slurm.sh a        # (a) only
#   bash scripts/test_slurm.sh b        # (b) only
#
# Needs root (slurmd launches jobs as their user) and Debian's slurm-wlm and munge, which it
# installs with apt-get if missing (scripts/setup.sh lists them).
set -euo pipefail

parts="${1:-ab}"
case "$parts" in a | b | ab) ;; *) echo "usage: $0 [a|b|ab]" >&2; exit 2 ;; esac
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
datagen="$repo/target/debug/datagen"
trainer="$repo/target/debug/trainer"
python="${TRAINER_PYTHON:-$repo/.venv/bin/python}"
# Training steps of (b): enough to signal the sbatch job mid-run, after its third step.
train_steps=24
# Tasks of (b); TRAIN_TASKS=1 checks the Slurm launch path alone, without distribution.
train_tasks="${TRAIN_TASKS:-2}"
# Seconds to wait for the node to come up idle, and for each job.
node_timeout=60
job_timeout=900

fail() {
    echo "FAIL: $*" >&2
    exit 1
}

((EUID == 0)) || fail "run as root: slurmd must be root to start jobs"
for bin in "$datagen" "$trainer"; do
    [[ -x "$bin" ]] || fail "missing $bin: run cargo build -p datagen -p trainer --bins"
done
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v munged >/dev/null; then
    echo "==> installing slurm-wlm and munge"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q >/dev/null
    apt-get install -y -q slurm-wlm munge >/dev/null
fi

work="$(mktemp -d /tmp/test_slurm.XXXXXX)"
chmod 700 "$work"
daemon_pids=()
cleanup() {
    local status=$?
    if [[ -n "${SLURM_CONF:-}" ]] && ((${#daemon_pids[@]})); then
        # Our own controller: its jobs are only this script's. Let their steps end first.
        scancel --quiet --full --user="$(id -un)" 2>/dev/null || true
        for _ in $(seq 100); do [[ -z "$(squeue -h 2>/dev/null)" ]] && break; sleep 0.1; done
    fi
    # One at a time, newest first (slurmd, slurmctld, munged: each needs the next to shut down
    # cleanly): SIGTERM, then SIGKILL after 10 s.
    for ((i = ${#daemon_pids[@]} - 1; i >= 0; i--)); do
        local pid="${daemon_pids[i]}"
        kill "$pid" 2>/dev/null || true
        for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
        kill -9 "$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
    done
    if ((status != 0)); then
        for log in "$work"/log/*.log "$work"/log/*.out; do
            [[ -s "$log" ]] && { echo "--- tail of $log"; tail -n 20 "$log"; }
        done >&2
    fi
    if [[ "${KEEP:-0}" == 1 ]]; then echo "kept $work"; else rm -rf "$work"; fi
    exit "$status"
}
trap cleanup EXIT

# Inputs handled according to a `datagen build` summary line ("worker 0/2: 2 ok, 0 skipped, 1 failed ...").
inputs_of() {
    sed -n 's/^worker [0-9]*\/[0-9]*: \([0-9]*\) ok, \([0-9]*\) skipped, \([0-9]*\) failed.*/\1+\2+\3/p' <<<"$1"
}

# Two free TCP ports on loopback for slurmctld and slurmd.
free_ports() {
    "$python" -c '
import socket
socks = [socket.socket() for _ in range(2)]
for s in socks: s.bind(("127.0.0.1", 0))
print(*(s.getsockname()[1] for s in socks))'
}

mkdir -p "$work"/{munge,state,spool,log,run}
host="$(hostname -s)"
t0=$SECONDS

echo "==> munged (private key and socket in $work/munge)"
dd if=/dev/urandom of="$work/munge/munge.key" bs=1024 count=1 status=none
chmod 400 "$work/munge/munge.key"
socket="$work/munge/munge.socket"
munged --foreground --force --key-file="$work/munge/munge.key" --socket="$socket" \
    --pid-file="$work/munge/munged.pid" --seed-file="$work/munge/munged.seed" \
    --log-file="$work/log/munged.log" >>"$work/log/munged.log" 2>&1 &
daemon_pids+=($!)
for _ in $(seq 50); do [[ -S "$socket" ]] && break; sleep 0.1; done
munge --socket="$socket" --no-input | unmunge --socket="$socket" >/dev/null || fail "munge round trip"

read -r ctld_port slurmd_port < <(free_ports)
# The node as slurmd detects it (CPUs, sockets, cores, memory), minus the uptime field.
node_line="$(slurmd -C | head -n 1 | sed 's/ UpTime=.*//')"
[[ "$node_line" == NodeName=* ]] || fail "slurmd -C printed: $node_line"
node="${node_line#NodeName=}"
node="${node%% *}"
export SLURM_CONF="$work/slurm.conf"
cat >"$SLURM_CONF" <<EOF
# One-node test cluster of scripts/test_slurm.sh; everything under $work.
ClusterName=cognvs-test
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
# A requeued job may start again only once its old credential has expired (cred_expire, 120 s by
# default, which slurmctld holds it for): 10 s here keeps the requeue test short. Starting it
# sooner fails ("Job credential revoked") whenever slurmd still remembers the old instance.
AuthInfo=socket=$socket,cred_expire=10
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/run/slurmctld.pid
SlurmdPidFile=$work/run/slurmd.pid
SlurmctldLogFile=$work/log/slurmctld.log
SlurmdLogFile=$work/log/slurmd.log
# No cgroups in this container: track processes through /proc, bind nothing.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SwitchType=switch/none
SchedulerType=sched/backfill
# CPUs are the only consumable resource; memory requests are checked against RealMemory only.
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
$node_line NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=test Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF

echo "==> slurmctld and slurmd (ports $ctld_port, $slurmd_port)"
# In the foreground (-D) so that their pids are ours to stop; they also log to stderr.
slurmctld -D -i -f "$SLURM_CONF" >"$work/log/slurmctld.stderr" 2>&1 &
daemon_pids+=($!)
slurmd -D -f "$SLURM_CONF" -N "$node" >"$work/log/slurmd.stderr" 2>&1 &
daemon_pids+=($!)
deadline=$((SECONDS + node_timeout))
until [[ "$(sinfo -h -N -n "$node" -o %t 2>/dev/null)" == idle ]]; do
    ((SECONDS < deadline)) || fail "node $node not idle after ${node_timeout}s: $(sinfo -N 2>&1)"
    sleep 0.5
done
echo "daemons up, node idle, in $((SECONDS - t0)) s"
sinfo -N -l

cpus="$(sed -n 's/.*CPUs=\([0-9]*\).*/\1/p' <<<"$node_line")"

if [[ "$parts" == *a* ]]; then
    echo "==> (a) scripts/build_corpus.sbatch as a 2-task array over a synthetic corpus"
    ta=$SECONDS
    printf 'width = 48\nheight = 32\nframes = 9\n' >"$work/scene.toml"
    "$datagen" synth-corpus --videos-per-layout 1 --out "$work/trees" --config "$work/scene.toml" \
        --corpus-out "$work/corpus_slurm" >/dev/null
    # The same corpus built by one worker outside Slurm.
    one="$(env -u SLURM_ARRAY_TASK_COUNT -u SLURM_ARRAY_TASK_ID -u SLURM_ARRAY_TASK_MIN -u JOB_COMPLETION_INDEX \
        "$datagen" build --config "$work/trees/corpus.toml" --out "$work/corpus_one")"
    echo "  one worker: $one"
    # The sbatch script runs ./target/release/datagen from the submit folder: give it one whose
    # target/release/datagen is the dev build under test.
    mkdir -p "$work/submit/target/release"
    ln -s "$datagen" "$work/submit/target/release/datagen"
    # Command-line options override the script's #SBATCH lines (sized for a real cluster).
    ts=$SECONDS
    (cd "$work/submit" && sbatch --wait --array=0-1 --cpus-per-task=1 --mem=1G --time=00:15:00 \
        --output="$work/log/corpus-%A_%a.out" "$repo/scripts/build_corpus.sbatch" "$work/trees/corpus.toml") \
        || fail "the corpus job array failed"
    echo "array job ran in $((SECONDS - ts)) s"
    logs=("$work"/log/corpus-*_0.out "$work"/log/corpus-*_1.out)
    for log in "${logs[@]}"; do [[ -f "$log" ]] || fail "no log of array task: $log"; done
    # Each task ran as its own worker of 2 and together they covered every input once (were the
    # array variables ignored, both would build everything and the contents would still agree).
    built=0
    for task in 0 1; do
        line="$(grep -h "^worker $task/2: " "$work"/log/corpus-*_"$task".out)" || fail "task $task did not run as worker $task/2"
        echo "  $line"
        built=$((built + $(inputs_of "$line")))
    done
    ((built == $(inputs_of "$one"))) || fail "the 2 tasks handled $built inputs, one worker $(inputs_of "$one")"
    "$python" - "$work/corpus_one" "$work/corpus_slurm" <<'EOF'
import hashlib, pathlib, sys
import pyarrow.parquet as pq

def content(folder):
    """(clip id, hash of every encoded frame and co-visibility mask) of each clip in finished shards."""
    found = set()
    for shard in sorted(pathlib.Path(folder).glob("shard-*.parquet")):
        if not shard.with_name(shard.name + ".stats.json").exists():
            sys.exit(f"{shard} has no stats marker")
        for row in pq.read_table(shard, columns=["clip_id", "frames", "trajectories"]).to_pylist():
            h = hashlib.blake2b()
            for frame in row["frames"]:
                h.update(frame)
            for trajectory in row["trajectories"]:
                for mask in trajectory["covisible_mask"]:
                    h.update(mask)
            key = (row["clip_id"], h.hexdigest())
            if key in found:
                sys.exit(f"duplicate clip {row['clip_id']} in {folder}")
            found.add(key)
    return found

one, slurm = content(sys.argv[1]), content(sys.argv[2])
if not one:
    sys.exit("the one-worker build produced no clips")
if one != slurm:
    sys.exit(f"2-task array differs from one worker: only one-worker {sorted(one - slurm)[:3]}, only array {sorted(slurm - one)[:3]}")
print(f"2-task array equals one worker: {len(one)} clips, identical frames and masks")
EOF
    echo "(a) passed in $((SECONDS - ta)) s"
fi

if [[ "$parts" == *b* ]]; then
    echo "==> (b) $train_tasks-task srun of trainer pretrain on configs/pretrain_tiny.toml"
    tb=$SECONDS
    "$datagen" synth --config <(printf 'width = 96\nheight = 64\nframes = 17\nseed = 4\n') --out "$work/seq" >/dev/null
    printf '[clip]\nlength = 9\nstride = 4\n' >"$work/pairs.toml"
    "$datagen" pairs "$work/seq" --out "$work/pairs" --config "$work/pairs.toml" --seed 0 >/dev/null
    # Global batch: one clip per rank.
    sed -e "s/^steps = .*/steps = $train_steps/" -e "s/^batch_size = [0-9]*/batch_size = $train_tasks/" -e 's/^checkpoint_every = .*/checkpoint_every = 8/' \
        -e 's/^validate_every = .*/validate_every = 0/' "$repo/configs/pretrain_tiny.toml" >"$work/pretrain.toml"
    mkdir -p "$work/runs"
    ((cpus >= train_tasks)) || fail "this node has $cpus CPU(s); (b) needs $train_tasks"
    ts=$SECONDS
    # Short error messages in the task logs, not backtraces; one thread per task, as
    # scripts/train.sbatch sets it (--cpus-per-task), so that both runs reduce in the same order.
    OMP_NUM_THREADS=1 RUST_BACKTRACE=0 RUST_LIB_BACKTRACE=0 srun --nodes=1 --ntasks="$train_tasks" --cpus-per-task=1 --mem=4G --time=00:15:00 --kill-on-bad-exit=1 \
        --output="$work/log/pretrain-%t.out" \
        "$trainer" pretrain --config "$work/pretrain.toml" --shards "$work/pairs" --out "$work/runs/run" \
        || fail "srun of trainer pretrain failed (exit $?); task logs: $(tail -n 5 "$work"/log/pretrain-*.out)"
    echo "srun ran in $((SECONDS - ts)) s"
    runs=()
    for dir in "$work"/runs/*/; do [[ -d "$dir/checkpoints" ]] && runs+=("$dir"); done
    ((${#runs[@]} == 1)) || fail "expected one run folder with checkpoints, found ${#runs[@]}: $(ls "$work/runs")"
    [[ -d "${runs[0]}/checkpoints/step-$(printf %08d "$train_steps")/transformer" ]] \
        || fail "no final checkpoint in ${runs[0]}: $(ls "${runs[0]}/checkpoints")"
    # One line per step: only one rank logs.
    lines="$(wc -l <"${runs[0]}/metrics.jsonl")"
    ((lines == train_steps)) || fail "${runs[0]}/metrics.jsonl has $lines lines for $train_steps steps"
    uninterrupted="${runs[0]}"

    echo "==> (b) scripts/train.sbatch preempted by SIGUSR1 mid-run, requeued, resumed"
    # The script runs ./target/release/trainer from the submit folder: the dev build under test.
    mkdir -p "$work/submit/target/release"
    ln -sf "$trainer" "$work/submit/target/release/trainer"
    preempted="$work/runs/preempted"
    ts=$SECONDS
    # Command-line options override the script's #SBATCH lines (sized for a GPU cluster).
    job="$(cd "$work/submit" && TRAINER_DEVICE=cpu RUST_BACKTRACE=0 sbatch --parsable --nodes=1 \
        --ntasks-per-node="$train_tasks" --gpus-per-node=0 --cpus-per-task=1 --mem=4G --time=00:15:00 \
        --output="$work/log/train-sbatch.out" "$repo/scripts/train.sbatch" "$work/pretrain.toml" "$work/pairs" "$preempted")"
    job="${job%%;*}"
    deadline=$((SECONDS + job_timeout))
    until (($(cat "$preempted/metrics.jsonl" 2>/dev/null | wc -l) >= 3)); do
        ((SECONDS < deadline)) || fail "job $job logged no 3 steps: $(scontrol show job "$job" 2>&1 | head -n 5)"
        sleep 0.2
    done
    scancel --signal=USR1 "$job"
    # Requeued, started again and completed: Restarts=1, JobState=COMPLETED.
    until [[ "$(scontrol show job "$job" -o 2>/dev/null)" =~ JobState=COMPLETED.*Restarts=1 ]]; do
        state="$(scontrol show job "$job" -o 2>/dev/null)"
        [[ "$state" =~ JobState=(FAILED|CANCELLED|TIMEOUT|NODE_FAIL|OUT_OF_MEMORY) ]] && fail "job $job: $state"
        ((SECONDS < deadline)) || fail "job $job not requeued and completed in time: $state"
        sleep 0.5
    done
    echo "preempted, requeued and resumed job ran in $((SECONDS - ts)) s"
    log="$work/log/train-sbatch.out"
    grep -q "SIGUSR1: stopped after step" "$log" || fail "no preemption checkpoint in $log"
    grep -q "trainer preempted (exit 75): requeueing job $job" "$log" || fail "the script did not requeue on 75: $log"
    grep -q "restart 1 of job $job: resuming" "$log" || fail "the requeued job did not resume: $log"
    "$python" - "$uninterrupted" "$preempted" "$train_steps" <<'EOF'
import json, pathlib, sys

uninterrupted, preempted, steps = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), int(sys.argv[3])

def losses(run):
    return [json.loads(line)["loss"] for line in (run / "metrics.jsonl").read_text().splitlines() if "loss" in line]

a, b = losses(uninterrupted), losses(preempted)
if len(a) != steps or a != b:
    sys.exit(f"losses differ: uninterrupted {a}, preempted and resumed {b}")
weights = f"checkpoints/step-{steps:08d}/transformer/diffusion_pytorch_model.safetensors"
if (uninterrupted / weights).read_bytes() != (preempted / weights).read_bytes():
    sys.exit(f"{weights} differs between the uninterrupted and the preempted run")
print(f"preempted run equals the uninterrupted one: {steps} losses, final weights byte for byte")
EOF
    echo "(b) passed in $((SECONDS - tb)) s"
fi
echo "test_slurm: all requested parts passed"
