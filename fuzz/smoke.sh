#!/usr/bin/env bash
# Time-boxed run of every fuzz target on the STABLE toolchain (cargo-fuzz, --sanitizer none):
# builds the targets and the seed corpus, then runs each target for FUZZ_SECONDS seconds
# (default 15), one after another, under the limits of issue 20: no input may run longer
# than 10 s (-timeout), the process may not exceed 2 GiB of RSS (-rss_limit_mb) and no
# allocation may succeed beyond a 3 GiB address space (ulimit -v: a multi-GB reservation
# aborts, which libFuzzer reports as a crash). Prints one line per target:
#   target execs seconds peak_rss_mb result
# and exits non-zero on the first crash, timeout or leak of memory (the reproducer is in
# fuzz/artifacts/<target>/).
#
#   fuzz/smoke.sh                       # CI smoke run: 11 targets x 15 s
#   FUZZ_SECONDS=3600 FUZZ_RUNS=10000000 fuzz/smoke.sh
#                                       # the long run: 10 M executions or 1 h per target
#   FUZZ_TARGETS="npy ply" fuzz/smoke.sh
set -euo pipefail
cd "$(dirname "$0")/.."

SECONDS_PER_TARGET=${FUZZ_SECONDS:-15}
# 0 = no cap on executions (libFuzzer's -runs=-1); the time box alone ends the run.
RUNS=${FUZZ_RUNS:-0}
[ "$RUNS" -gt 0 ] || RUNS=-1
TARGET_DIR=${FUZZ_TARGET_DIR:-target/fuzz}
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
python3 fuzz/build_corpus.py >/dev/null
cargo fuzz build --sanitizer none --target-dir "$TARGET_DIR" >/dev/null
TARGETS=${FUZZ_TARGETS:-$(cargo fuzz list)}
mkdir -p "$TARGET_DIR/logs"
printf '%-18s %12s %8s %12s %s\n' target execs seconds peak_rss_mb result
status=0
for t in $TARGETS; do
    log="$TARGET_DIR/logs/$t.log"
    set +e
    (
        ulimit -v $((3 * 1024 * 1024))
        cargo fuzz run --sanitizer none --target-dir "$TARGET_DIR" "$t" "fuzz/corpus/$t" -- \
            -max_total_time="$SECONDS_PER_TARGET" -runs="$RUNS" -timeout=10 -rss_limit_mb=2048 \
            -max_len=65536 -print_final_stats=1 -close_fd_mask=1
    ) >"$log" 2>&1
    rc=$?
    set -e
    execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo '?')
    secs=$(grep -o 'Done [0-9]* runs in [0-9]* second' "$log" | grep -o 'in [0-9]*' | grep -o '[0-9]*' || echo '?')
    rss=$(grep -o 'stat::peak_rss_mb: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo '?')
    result=ok
    if [ "$rc" -ne 0 ]; then
        result="FAILED (rc $rc, see $log and fuzz/artifacts/$t/)"
        status=1
    fi
    printf '%-18s %12s %8s %12s %s\n' "$t" "$execs" "$secs" "$rss" "$result"
done
exit $status
