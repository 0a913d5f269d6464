#!/usr/bin/env bash
# The radio front end end to end: per seed, simulate a scenario's track with its sampled
# channel, estimate the paths from the channel, and run the filter on the simulator's ideal
# component log and on the estimated one with the same seed. Prints one row per seed and the
# mean MAE of both.
#
#   tests/radio/end_to_end.sh SCENARIO SEEDS PARTICLES OUT [run flags...]
#   tests/radio/end_to_end.sh urban 10 1000 out/e2e-urban --preset urban
#
# FIRST_SEED=N starts at seed N (default 1).
# Uses target/release/echomap-agent (built first).
set -euo pipefail
cd "$(dirname "$0")/../.."
scenario=$1 seeds=$2 particles=$3 out=$4
shift 4
cargo build --release -q -p echomap-agent
agent=target/release/echomap-agent
mkdir -p "$out"
summary() {
    python3 -c 'import json,sys; d=json.load(open(sys.argv[1])); print("%.3f %.3f %.3f" % (d["mae_mean_m"], d["mae_final_m"], d["rmse_max_m"]))' "$1/summary.json"
}
printf '%-5s %-28s %-28s %s\n' seed "ideal: mean/final/max RMSE" "estimated: mean/final/max RMSE" "estimator"
first=${FIRST_SEED:-1}
for s in $(seq "$first" $((first + seeds - 1))); do
    d=$out/seed$s
    "$agent" simulate --scenario "$scenario" --seed "$s" --cir --out "$d/sim" > /dev/null
    t0=$(date +%s.%N)
    est=$("$agent" estimate "$d/sim" --out "$d/est")
    t1=$(date +%s.%N)
    "$agent" run --log "$d/sim" --particles "$particles" --seed "$s" --quiet "$@" --out "$d/run-ideal" > /dev/null
    "$agent" run --log "$d/est" --particles "$particles" --seed "$s" --quiet "$@" --out "$d/run-est" > /dev/null
    printf '%-5s %-28s %-28s %s (%.0f s)\n' "$s" "$(summary "$d/run-ideal")" "$(summary "$d/run-est")" \
        "$(echo "$est" | sed 's/ →.*//')" "$(echo "$t1 - $t0" | bc)"
done | tee "$out/table.txt"
python3 - "$out/table.txt" <<'PY'
import sys
rows = [l.split() for l in open(sys.argv[1]) if l.strip() and l.split()[0].isdigit()]
ideal = [float(r[1]) for r in rows]
est = [float(r[4]) for r in rows]
mi, me = sum(ideal) / len(ideal), sum(est) / len(est)
print(f"mean MAE over {len(rows)} seeds: ideal {mi:.2f} m, estimated {me:.2f} m, ratio {me / mi:.2f}")
PY
