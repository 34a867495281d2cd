#!/usr/bin/env bash
# Property-based fuzzing of a live sdhop-serve against its own openapi.yaml
# (schemathesis, every check, settings in schemathesis.toml): starts the
# release server with the shipped models on a free loopback port, fuzzes
# it with a fixed seed and a bounded number of examples, and fails on any
# failure. usage: .ci/fuzz.sh [EXAMPLES] [SEED]
set -euo pipefail
cd "$(dirname "$0")/.."
examples=${1:-200}
seed=${2:-20261124}
cargo build --release --bin sdhop-serve
out=$(mktemp -d)
./target/release/sdhop-serve --addr 127.0.0.1:0 > "$out/stdout" 2> "$out/stderr" &
pid=$!
trap 'kill $pid 2>/dev/null || true; wait $pid 2>/dev/null || true' EXIT
for _ in $(seq 1 300); do
  grep -q "^listening on" "$out/stdout" 2>/dev/null && break
  sleep 0.1
done
addr=$(sed -n 's/^listening on //p' "$out/stdout")
[ -n "$addr" ] || { echo "the server did not start:"; cat "$out/stderr"; exit 1; }
for _ in $(seq 1 600); do
  curl -sf "http://$addr/health/ready" >/dev/null && break
  sleep 0.1
done
timeout 300 schemathesis run openapi.yaml --url "http://$addr" --checks all \
  --seed "$seed" --max-examples "$examples" --request-timeout 60 --workers 1 \
  --no-color
# The server is still healthy after the fuzzing.
curl -sf "http://$addr/health/ready"
echo
