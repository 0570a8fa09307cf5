#!/bin/bash
# The paper's ModelNet40 view-count ablation on a Slurm cluster, one GPU per job, from a login
# node (Hydra's submitit launcher submits one array job and waits for it; run this in tmux/screen).
# A preempted or timed-out job is requeued and goes on from its own last.pt.
set -euo pipefail
cd "$(dirname "$0")/.."
make install                                     # .venv with mvtn-exp and the launchers
.venv/bin/mvtn-prepare dataset=modelnet40 dataset.root="${DATA:-data/ModelNet40}"   # build the cache once
.venv/bin/mvtn-train -m +experiment=modelnet_views_ablation \
    hydra/launcher=slurm hydra.launcher.partition="${PARTITION:?set PARTITION}" \
    hydra.launcher.timeout_min=1440 hydra.launcher.array_parallelism=8 \
    dataset.root="${DATA:-data/ModelNet40}" device=cuda dataset.num_workers=6 \
    "$@"
# If this process is gone when the jobs end, write the summary yourself:
#   .venv/bin/mvtn-train --summary outputs/train/multiruns/<sweep>
