#!/bin/sh
# The published study of docs/results.md, from the training runs to every generated section,
# as a clean checkout reproduces it (run from the repository's root, dammrl installed).
# Resumable: a training run already finished with the same settings is kept, so after an
# interruption the same command carries on; each study step reruns whole.
#   JOBS  processes per step (default 1: one core stays free for other work)
#   RUNS  where the training runs go (default runs/)
# Afterwards: commit dammrl_core/policies/reward*/seeds, docs/study, docs/results.md, README.md.
set -eu
JOBS=${JOBS:-1}
RUNS=${RUNS:-runs}
step() { echo "$(date -u +%H:%M:%S) $*"; }

# 12 training runs per reward (seeds 0-11), each evaluated on 7,000,000-7,000,099, shipped
# as the study reads them
for R in 1 2; do
  step "training Reward $R"
  dammrl train --reward "$R" --seeds 12 --out "$RUNS/r$R" --jobs "$JOBS" \
    --ship-seeds "dammrl_core/policies/reward$R/seeds"
done
# the published study: 300 fresh seeds in 3 sets, every row, three conditions
step "study, first range (7,300,000-7,300,299)"
dammrl study --seeds 7300000:7300300 --sets 3 --jobs "$JOBS" --out docs/study \
  --results docs/results.md --results README.md
# the second disjoint range: the paper's configurations, which every verdict needs
step "study, second range (7,400,000-7,400,299)"
dammrl study --seeds 7400000:7400300 --sets 3 --rows paper --jobs "$JOBS" --out docs/study/second
# how the verdicts depend on IK solve time: the reference machine's scaled, and this computer's
step "solve-time sweep (7,300,000-7,300,099)"
dammrl study --seeds 7300000:7300100 --sets 1 --rows paper --jobs "$JOBS" \
  --conditions ikpy-real-x0.25,ikpy-real-x0.5,ikpy-real,ikpy-real-x2,ikpy-measured \
  --out docs/study/solve_time
step "findings: both ranges side by side"
dammrl verdicts docs/study docs/study/second --results docs/results.md
step "published"
