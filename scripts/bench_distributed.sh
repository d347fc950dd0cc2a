#!/usr/bin/env bash
# Multi-process training on this CPU: step time of the mid-size config
# (scripts/bench_train.sh's: 8 blocks, 12 heads x 64, tiny VAE, 9 frames at 64x80) at global
# batch 2 on 1 rank (2 threads) and on 2 ranks x 1 thread (Gloo, ZeRO-0 and ZeRO-2) — the same
# arithmetic, so the difference is the cost of synchronization — with each rank's peak RSS; the
# exposed communication at 2 ranks (`trainer comm-cost`: ZeRO-0 and ZeRO-2 each with the real
# collectives and with local no-ops, interleaved in rounds of COST_STEPS steps per variant); then
# the all-reduce bandwidth between 2 local processes (`trainer comm-check`).
# Usage: scripts/bench_distributed.sh [STEPS (8)]   (PROFILE=release for a release build;
#        COST_ROUNDS (3) and COST_STEPS (3) size the comm-cost part, CHECK_MIB (64) and
#        CHECK_ITERATIONS (9) the bandwidth part)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

steps="${1:-8}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
PROFILE="${PROFILE:-dev}" source scripts/bench_common.sh
for stage in 0 2; do
    sed -e "s|^transformer = .*|transformer = \"$work/mid.json\"\nzero_text_embedding = true|" -e "s|^steps = .*|steps = $steps|" \
        -e "s|^batch_size = .*|batch_size = 2|" -e "s|^checkpoint_every = .*|checkpoint_every = 1000000|" \
        -e "s|^validate_every = .*|validate_every = 0|" configs/pretrain_tiny.toml >"$work/zero$stage.toml"
    printf '\n[distributed]\nzero_stage = %s\n' "$stage" >>"$work/zero$stage.toml"
done

median_step() {
    python3 -c "
import json, statistics
s = [json.loads(l)['seconds'] for l in open('$1/metrics.jsonl')][2:]
print(f'{statistics.median(s):.3f} s (range {min(s):.3f}-{max(s):.3f})')"
}

# Runs a command with its output in LOG, printing the log and failing if it fails.
logged() {
    local log="$1"
    shift
    "$@" >"$log" 2>&1 || { echo "failed: $*" >&2; cat "$log" >&2; return 1; }
}

OMP_NUM_THREADS=2 logged "$work/single.log" /usr/bin/time -f '%M' -o "$work/single.rss" "$trainer" pretrain \
    --config "$work/zero0.toml" --shards "$work/pairs" --out "$work/single"
echo "1 rank x batch 2 (2 threads): median step $(median_step "$work/single"), peak RSS $(( $(cat "$work/single.rss") / 1024 )) MiB"
port=29650
for stage in 0 2; do
    port=$((port + 1))
    pids=()
    for rank in 0 1; do
        RANK=$rank WORLD_SIZE=2 MASTER_ADDR=127.0.0.1 MASTER_PORT=$port OMP_NUM_THREADS=1 \
            logged "$work/zero$stage-$rank.log" /usr/bin/time -f '%M' -o "$work/zero$stage-$rank.rss" "$trainer" \
            pretrain --config "$work/zero$stage.toml" --shards "$work/pairs" --out "$work/zero$stage" &
        pids+=($!)
    done
    for pid in "${pids[@]}"; do wait "$pid"; done
    echo "2 ranks x batch 1 (1 thread each), ZeRO-$stage: median step $(median_step "$work/zero$stage"), peak RSS rank 0 $(( $(cat "$work/zero$stage-0.rss") / 1024 )) MiB, rank 1 $(( $(cat "$work/zero$stage-1.rss") / 1024 )) MiB"
done
python3 - "$work" <<'PY'
import json, sys
work = sys.argv[1]
def losses(run): return [json.loads(l)["loss"] for l in open(f"{work}/{run}/metrics.jsonl")]
a, b, c = losses("single"), losses("zero0"), losses("zero2")
print("max relative loss difference: 2 ranks vs 1 %.2e, ZeRO-2 vs ZeRO-0 %.2e" % (
    max(abs(x - y) / abs(y) for x, y in zip(b, a)), max(abs(x - y) / abs(y) for x, y in zip(c, b))))
PY
OMP_NUM_THREADS=1 .venv/bin/torchrun --nproc-per-node 2 --master-port $((port + 1)) --no-python "$trainer" comm-cost \
    --config "$work/zero0.toml" --rounds "${COST_ROUNDS:-3}" --steps "${COST_STEPS:-3}" 2>"$work/cost.log" \
    | tail -1 >"$work/cost.json" || { cat "$work/cost.log"; exit 1; }
python3 - "$work/cost.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
step = {(v["zero_stage"], v["collectives"]): v["median_step_seconds"] for v in r["variants"]}
parts = [f"ZeRO-{z} {100 * r['exposed_fraction'][f'zero{z}']:.1f} % (real {step[(z, 'real')]:.3f} s, no-op {step[(z, 'noop')]:.3f} s)"
         for z in (0, 2)]
print(f"exposed communication, 2 ranks x batch 1 ({r['backend']}, {r['rounds']} rounds x {r['steps']} steps, "
      f"medians): {', '.join(parts)}; ZeRO-2 / ZeRO-0 step {r['zero2_over_zero0']:.3f}")
PY
logged "$work/check.log" .venv/bin/torchrun --nproc-per-node 2 --master-port $((port + 2)) --no-python "$trainer" \
    comm-check --mib "${CHECK_MIB:-64}" --iterations "${CHECK_ITERATIONS:-9}"
grep '^all-reduce [0-9]' "$work/check.log"
