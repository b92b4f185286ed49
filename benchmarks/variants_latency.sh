#!/usr/bin/env bash
# Act, update and env-step latency of all nine agents on one task (benchmarks/train_throughput.py --skip-chunk),
# one JSON per agent under OUT_DIR (default benchmarks/results/variants). Compiles all agents side by side first
# (--repeats 1, filling XLA's persistent cache), then times them one after another from the cache, so that no
# measurement shares the GPU with another process.
#   bash benchmarks/variants_latency.sh [TASK] [SEEDS]
set -eu
task=${1:-cartpole-swingup}
seeds=${2:-1}
out=${OUT_DIR:-benchmarks/results/variants}
agents="tdmpc2 cfc-zp-det cfc-zp-stoch cfc-op-det cfc-op-stoch ltc-zp-det ltc-zp-stoch ltc-op-det ltc-op-stoch"
mkdir -p "$out" runs/jaxcache
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-runs/jaxcache}
export JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0 XLA_PYTHON_CLIENT_MEM_FRACTION=0.1
here=$(dirname "$0")
for agent in $agents; do
    python3 "$here/train_throughput.py" --tasks "$task" --agent "$agent" --seeds "$seeds" --skip-chunk \
        --repeats 1 --out "/tmp/warm-$agent.json" >/dev/null 2>&1 &
done
wait
unset XLA_PYTHON_CLIENT_MEM_FRACTION
for agent in $agents; do
    python3 "$here/train_throughput.py" --tasks "$task" --agent "$agent" --seeds "$seeds" --skip-chunk \
        --repeats 15 --out "$out/$agent.json" 2>&1 | grep -v -i warp
done
