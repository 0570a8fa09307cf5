#!/bin/bash
# The speed/accuracy study (README "The speed/accuracy study"): the sweep, then its table and
# Pareto plot. JOBS=2 runs two jobs at a time with the joblib launcher (each gets half the cores).
set -euo pipefail
cd "$(dirname "$0")/.."
dir="outputs/train/multiruns/tradeoff-$(date +%Y%m%d-%H%M%S)"
.venv/bin/mvtn-train -m +experiment=tradeoff_synthetic hydra/launcher=joblib \
    hydra.launcher.n_jobs="${JOBS:-1}" hydra.sweep.dir="$dir" "$@"
.venv/bin/mvtn-tradeoff "$dir"
