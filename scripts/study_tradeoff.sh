#!/bin/bash
# The speed/accuracy study (README "The speed/accuracy study"): both sweeps, then a table and a
# Pareto plot for each (mvtn-tradeoff compares jobs of one dataset, so each half has its folder).
# JOBS=2 (default) runs two jobs at a time with the joblib launcher, each with half the cores;
# about 1.5 hours on a 2-core CPU. Extra arguments go to both sweeps.
set -euo pipefail
cd "$(dirname "$0")/.."
stamp="$(date +%Y%m%d-%H%M%S)"
for study in tradeoff_synthetic tradeoff_synthetic_views; do
    dir="outputs/train/multiruns/${study}-${stamp}"
    .venv/bin/mvtn-train -m +experiment="$study" hydra/launcher=joblib \
        hydra.launcher.n_jobs="${JOBS:-2}" hydra.sweep.dir="$dir" "$@"
    .venv/bin/mvtn-tradeoff "$dir"
done
