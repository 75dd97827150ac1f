#!/usr/bin/env bash
# Usage (root, for the namespaces): POLL=<tunnel poll period, µs> ./run.sh
# Two namespaces joined by a veth pair; a tunnel in each; publisher in A, subscriber in B.
set -u
TMP=$(mktemp)
B="$(dirname "$0")/target/release/iceoryx2-tunnel-bench"
ip netns add tba; ip netns add tbb
ip link add tbva type veth peer name tbvb
ip link set tbva netns tba; ip link set tbvb netns tbb
ip -n tba addr add 10.89.0.1/24 dev tbva; ip -n tbb addr add 10.89.0.2/24 dev tbvb
ip -n tba link set tbva up; ip -n tbb link set tbvb up; ip -n tba link set lo up; ip -n tbb link set lo up
POLL=${POLL:-100}
for size in 4096 65536 1048576 4194304; do
  ip netns exec tba $B tunnel tbA_ listen tcp/10.89.0.1:7449 $POLL & TA=$!
  ip netns exec tbb $B tunnel tbB_ connect tcp/10.89.0.1:7449 $POLL & TB=$!
  sleep 1
  ip netns exec tbb $B sub tbB_ 110 10 > "$TMP" & S=$!
  sleep 1
  ip netns exec tba $B pub tbA_ $size 110 50
  wait $S
  echo "size $size: $(cat "$TMP")"
  kill $TA $TB; wait $TA $TB 2>/dev/null
done
ip netns del tba; ip netns del tbb
