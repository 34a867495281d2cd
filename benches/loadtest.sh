#!/usr/bin/env bash
# HTTP load test of sdhop-serve from a second process on loopback, bounded
# in time: wrk POSTs CMU_KO8 development images (every tenth of each object)
# to /detect with one model and with all eight; then a 10x overload burst
# (ten times the queue size in connections) while the server's memory is
# sampled. Also runs the in-process throughput example for comparison.
# usage: benches/loadtest.sh [SECONDS] [DATA_ROOT]
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${1:-30}
root=${2:-../shared/data/cmu_ko8}
port=18090
out=$(mktemp -d)
ls "$root"/single/test/*/*.jpg | awk 'NR % 10 == 1' > "$out/images.txt"
echo "$(wc -l < "$out/images.txt") images"
cargo build --release --bin sdhop-serve --example throughput >/dev/null

echo "== in process"
./target/release/examples/throughput "$out/images.txt" "$secs" models/cup.safetensors
./target/release/examples/throughput "$out/images.txt" "$secs" models/*.safetensors

./target/release/sdhop-serve --addr 127.0.0.1:$port --queue-size 32 > "$out/serve.out" 2> "$out/serve.err" &
pid=$!
trap 'kill $pid 2>/dev/null || true' EXIT
until curl -sf "http://127.0.0.1:$port/health/ready" >/dev/null; do sleep 0.2; done
rss() { awk '/VmRSS/ {print $2 " kB"}' /proc/$pid/status; }
echo "server RSS after warm-up: $(rss)"

for query in "?model=cup" ""; do
  echo "== HTTP, 2 connections, query '$query'"
  IMAGES="$out/images.txt" QUERY="$query" wrk -t 1 -c 2 -d "${secs}s" --latency \
    -s benches/loadtest.lua "http://127.0.0.1:$port" | grep -E "Latency|50%|99%|Requests/sec|Non-2xx|requests in"
  echo "server RSS: $(rss)"
done

echo "== overload burst: 320 connections (10x the queue), all models"
( for _ in $(seq 1 20); do sleep 0.5; rss; done ) > "$out/rss.txt" &
IMAGES="$out/images.txt" QUERY="" wrk -t 2 -c 320 -d 10s --latency --timeout 30s \
  -s benches/loadtest.lua "http://127.0.0.1:$port" | grep -E "Latency|50%|99%|Requests/sec|Non-2xx|requests in|errors"
wait %2 2>/dev/null || true
echo "server RSS during the burst (max): $(sort -n "$out/rss.txt" | tail -1)"
curl -s "http://127.0.0.1:$port/metrics" | grep -E '^sdhop_queue_requests_total|^sdhop_http_requests_total\{route="/detect"'
kill -TERM $pid; wait $pid || true
echo "(files in $out)"
