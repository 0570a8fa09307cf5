"""Hydra config files of the CLIs (``train.yaml`` and its groups, ``render.yaml``, ``bench.yaml``, ...).

Importing this package (Hydra does, to find the files) registers two resolvers:

- ``mvtn.pid``: run dirs are ``<time>-<pid>``, so two runs started in the same second never share
  a folder. Cached (like Hydra's ``now``): a sweep resolves its folder once, in the process that
  launches it, and Hydra copies that cache into every job's config, so jobs that run in other
  processes (joblib, submitit, a requeued Slurm job) land in the announced sweep folder.
- ``mvtn.dirname``: a sweep job's folder name from its overrides (``views=1,seed=0`` ->
  ``views-1_seed-0``) with nothing the command line would have to quote (no ``=``, ``,``,
  brackets, quotes or spaces), so the ``resume with: mvtn-train ckpt_path=...`` a job prints runs
  as printed.
"""
import os
import re

from omegaconf import OmegaConf


def job_dirname(overrides: str) -> str:
    """Hydra's ``override_dirname`` (``k=v,k=v``) as a folder name that needs no quoting."""
    return re.sub(r"[^A-Za-z0-9_.+:@%-]", "", overrides.replace("=", "-").replace(",", "_"))


OmegaConf.register_new_resolver("mvtn.pid", os.getpid, replace=True, use_cache=True)
OmegaConf.register_new_resolver("mvtn.dirname", job_dirname, replace=True)
